use clap::{Parser, Subcommand};
use std::process::ExitCode;
use vkterrain::app::commands::{self, ErrorsArgs, RenderArgs};
use vkterrain::app::viewer::ViewArgs;

/// vkterrain: a Vulkan terrain renderer with a GPU-rasterized screen-space error
/// quadtree (Yusuf, Mostafa and Elarif), run as two activities on two queues.
#[derive(Parser)]
#[command(name = "vkterrain", version, about, long_about = None, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    /// With no subcommand: the viewer's options.
    #[command(flatten)]
    view: ViewArgs,
}

#[derive(Subcommand)]
enum Command {
    /// Open a window with both activities live (the default).
    View(ViewArgs),
    /// Render one frame headless to a PNG and print stats as JSON.
    Render(RenderArgs),
    /// Compute error generations on the GPU and print their cost as JSON.
    Errors(ErrorsArgs),
    /// Run a camera path headless and write frames.csv, summary.json, plot.png, trace.json.
    Bench(vkterrain::app::bench::BenchArgs),
    /// Sweep delta and the distance factor on CPU along a path: triangles against the
    /// audited maximum error (quality.csv, quality.json, quality.png).
    Quality(vkterrain::app::quality::QualityArgs),
    /// Draw a trace (bench or view --trace) as a picture: one lane per thread and queue.
    Timeline(vkterrain::app::timeline::TimelineArgs),
    /// Prepare a terrain of any size into a tile archive (PMTiles), window by window.
    Prepare(vkterrain::app::prepare::PrepareArgs),
    /// Read every tile of an archive and check it (sizes, layout, checksums).
    Check(vkterrain::app::prepare::CheckArgs),
    /// Fly low over a terrain headless, its tiles streamed through a bounded cache, and
    /// report what was read, held and drawn over the bound, as JSON.
    Stream(vkterrain::app::stream::StreamArgs),
}

fn main() -> ExitCode {
    // A message that cannot be written (standard error or output closed, a full disk)
    // ends the run with exit code 1, not a panic's 101 and its backtrace (which could
    // not be written either). `print!` and `eprint!` panic so.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let text = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if text.starts_with("failed printing to std") {
            std::process::exit(1);
        }
        default_hook(info);
    }));
    let logging = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Colour codes only on a terminal: a log file or CI gets plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    match tracing_subscriber::EnvFilter::try_from_default_env() {
        // RUST_LOG asks for a log: tracing's own lines, with times and places.
        Ok(filter) => logging.with_env_filter(filter).init(),
        // Else warnings read like the program's other messages.
        Err(_) => logging.with_env_filter("warn").event_format(Plain).init(),
    }
    // Usage errors are one line naming the option, exit code 2; help and version print
    // as usual.
    let mut cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) if !e.use_stderr() => {
            let _ = e.print();
            return ExitCode::SUCCESS;
        }
        Err(e) => {
            let text = e.render().to_string();
            let mut first =
                text.lines().next().unwrap_or("invalid arguments").trim_start_matches("error: ").to_string();
            // "the following required arguments were not provided:" lists the names on
            // the indented lines below it: keep them on the one line.
            if first.ends_with(':') {
                let names: Vec<&str> =
                    text.lines().skip(1).take_while(|l| l.starts_with("  ")).map(str::trim).collect();
                first = format!("{first} {}", names.join(", "));
            }
            // A value outside a fixed set: name the set on the same line.
            let possible = text.lines().find_map(|l| l.trim().strip_prefix("[possible values: "));
            match (possible, misplaced_input_hint(&e)) {
                (Some(values), _) => say(&format!("{first} (one of: {})", values.trim_end_matches(']'))),
                (None, Some(hint)) => say(&format!("{first}: did you mean {hint}?")),
                (None, None) => say(&first),
            }
            return ExitCode::from(2);
        }
    };
    // Each subcommand takes its terrain as TERRAIN or as --heightmap FILE.
    match &mut cli.command {
        None => cli.view.common.terrain.take_terrain(),
        Some(Command::View(a)) => a.common.terrain.take_terrain(),
        Some(Command::Render(a)) => a.common.terrain.take_terrain(),
        Some(Command::Errors(a)) => a.terrain.take_terrain(),
        Some(Command::Bench(a)) => a.common.terrain.take_terrain(),
        Some(Command::Quality(a)) => a.terrain.take_terrain(),
        Some(Command::Stream(a)) => a.terrain.take_terrain(),
        Some(Command::Prepare(a)) => a.input.extend(a.heightmap.take()),
        Some(Command::Timeline(_) | Command::Check(_)) => {}
    }
    let result = match &cli.command {
        None => vkterrain::app::viewer::view(&cli.view),
        Some(Command::View(a)) => vkterrain::app::viewer::view(a),
        Some(Command::Render(a)) => commands::render(a),
        Some(Command::Errors(a)) => commands::errors(a),
        Some(Command::Bench(a)) => vkterrain::app::bench::bench(a),
        Some(Command::Quality(a)) => vkterrain::app::quality::quality(a),
        Some(Command::Timeline(a)) => vkterrain::app::timeline::timeline(a),
        Some(Command::Prepare(a)) => vkterrain::app::prepare::prepare(a),
        Some(Command::Check(a)) => vkterrain::app::prepare::check(a),
        Some(Command::Stream(a)) => vkterrain::app::stream::stream(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            say(&error_chain(&e));
            ExitCode::from(vkterrain::app::cli::exit_code(&e))
        }
    }
}

/// The line that ends a run, on standard error; where it cannot be written the exit code
/// still says what happened.
fn say(line: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "vkterrain: {line}");
}

/// For a word the parser did not expect where an input goes (a second terrain, or a
/// file after a flag that takes none): the form that names one terrain.
fn misplaced_input_hint(e: &clap::Error) -> Option<String> {
    use clap::error::{ContextKind, ContextValue, ErrorKind};
    let one_terrain = "`vkterrain view FILE` or `vkterrain render FILE` (one terrain a run)".to_string();
    // Two words with no subcommand: clap took the second for a subcommand.
    if let (ErrorKind::ArgumentConflict, Some(ContextValue::String(word))) =
        (e.kind(), e.get(ContextKind::InvalidSubcommand))
    {
        return (!word.starts_with('-')).then_some(one_terrain);
    }
    let Some(ContextValue::String(arg)) = e.get(ContextKind::InvalidArg) else { return None };
    if e.kind() != ErrorKind::UnknownArgument || arg.starts_with('-') {
        return None;
    }
    let sub = std::env::args().skip(1).find(|a| !a.starts_with('-')).filter(|a| *a != *arg);
    Some(match sub.as_deref() {
        Some("prepare") => format!("`vkterrain prepare {arg} ... --out FILE` (every input before the options)"),
        Some("timeline") => "`vkterrain timeline --trace FILE --out FILE.png`".to_string(),
        Some(sub) => format!("`vkterrain {sub} FILE` or `vkterrain {sub} --heightmap FILE` (one terrain a run)"),
        None => one_terrain,
    })
}

/// The error and its causes on one line, each cause once: an error whose message already
/// ends with its cause's text (`path: {source}`) does not repeat it.
fn error_chain(e: &anyhow::Error) -> String {
    let mut line = e.to_string();
    for cause in e.chain().skip(1) {
        let text = cause.to_string();
        if !line.ends_with(&text) {
            line = format!("{line}: {text}");
        }
    }
    line
}

/// Warnings and errors as `vkterrain: warning: ...`, as the program's own notes print.
struct Plain;

impl<S, N> tracing_subscriber::fmt::FormatEvent<S, N> for Plain
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
    N: for<'a> tracing_subscriber::fmt::FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        ctx: &tracing_subscriber::fmt::FmtContext<'_, S, N>,
        mut writer: tracing_subscriber::fmt::format::Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result {
        let level = match *event.metadata().level() {
            tracing::Level::ERROR => "error",
            tracing::Level::WARN => "warning",
            _ => "note",
        };
        write!(writer, "vkterrain: {level}: ")?;
        ctx.field_format().format_fields(writer.by_ref(), event)?;
        writeln!(writer)
    }
}
