//! Where an archive's bytes come from: a local file (positioned reads), or a URL read
//! with HTTP range requests, which is what PMTiles is laid out for (the header, root
//! directory and metadata in the first 16 KiB; a tile is one range). A team shares one
//! archive on a web server or an object store this way.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

/// Is this "path" a URL (`http://` or `https://`)?
pub fn is_url(path: &Path) -> bool {
    let s = path.to_string_lossy().to_ascii_lowercase();
    s.starts_with("http://") || s.starts_with("https://")
}

/// How a path or URL is shown in messages: a URL's credentials (`user:password@`) are
/// replaced by `***@`, so that a log or a bug report does not leak them.
pub fn shown(path: &Path) -> String {
    let text = path.to_string_lossy();
    if !is_url(path) {
        return path.display().to_string();
    }
    let Some(scheme_end) = text.find("://").map(|i| i + 3) else { return text.into_owned() };
    let authority_end = text[scheme_end..].find(['/', '?', '#']).map_or(text.len(), |i| scheme_end + i);
    match text[scheme_end..authority_end].rfind('@') {
        Some(at) => format!("{}***{}", &text[..scheme_end], &text[scheme_end + at..]),
        None => text.into_owned(),
    }
}

pub enum Bytes {
    File(File),
    Http(Http),
    /// An archive made in memory: a terrain file cut into tiles at load.
    Memory(Vec<u8>),
}

pub struct Http {
    agent: ureq::Agent,
    url: String,
    len: u64,
}

impl Bytes {
    /// Opens a local file or a URL; the error says what went wrong, without the name.
    pub fn open(path: &Path) -> Result<(Bytes, u64), String> {
        if is_url(path) {
            let http = Http::open(&path.to_string_lossy())?;
            let len = http.len;
            return Ok((Bytes::Http(http), len));
        }
        let file = File::open(path).map_err(|e| e.to_string())?;
        let len = file.metadata().map_err(|e| e.to_string())?.len();
        Ok((Bytes::File(file), len))
    }

    /// Fills `buf` from `offset` (the caller has checked the range against the length).
    pub fn read_at(&self, buf: &mut [u8], offset: u64) -> Result<(), String> {
        match self {
            Bytes::File(f) => f.read_exact_at(buf, offset).map_err(|e| e.to_string()),
            Bytes::Http(h) => h.read_at(buf, offset),
            Bytes::Memory(m) => {
                let start = usize::try_from(offset).map_err(|e| e.to_string())?;
                buf.copy_from_slice(&m[start..start + buf.len()]);
                Ok(())
            }
        }
    }
}

impl Http {
    /// Timeouts for one request: a server that stops answering, or trickles, fails the
    /// read (the streamer then draws coarser and retries), it does not hang a thread.
    /// The overall limit covers connecting, a stalled pooled connection and the body.
    const CONNECT_S: u64 = 10;
    const READ_S: u64 = 30;
    const REQUEST_S: u64 = 60;

    fn open(url: &str) -> Result<Http, String> {
        let agent = ureq::AgentBuilder::new()
            .timeout_connect(std::time::Duration::from_secs(Self::CONNECT_S))
            .timeout_read(std::time::Duration::from_secs(Self::READ_S))
            .timeout(std::time::Duration::from_secs(Self::REQUEST_S))
            .build();
        // The length from a one-byte range: "Content-Range: bytes 0-0/LEN" (HEAD does
        // not always carry Content-Length).
        let response = Self::get(&agent, url, 0, 0)?;
        let len = match content_range(&response) {
            Some((0, 0, Some(len))) if len > 0 => len,
            _ => {
                return Err(format!(
                    "the server answered {} without a Content-Range length: it does not serve byte ranges",
                    response.status()
                ))
            }
        };
        let http = Http { agent, url: url.to_string(), len };
        // The last byte too: a length the server states but cannot serve (a proxy's
        // guess, a file cut short) fails here, not at the first tile past the real end.
        let mut last = [0u8];
        http.read_at(&mut last, len - 1)
            .map_err(|e| format!("reading its last byte (the server gives the length as {len} bytes): {e}"))?;
        Ok(http)
    }

    fn get(agent: &ureq::Agent, url: &str, first: u64, last: u64) -> Result<ureq::Response, String> {
        // Identity: a compressed body would not be the bytes of the range.
        let request = agent.get(url).set("Range", &format!("bytes={first}-{last}")).set("Accept-Encoding", "identity");
        let response = request.call().map_err(|e| match e {
            ureq::Error::Status(code, r) => format!("HTTP {code} {}", r.status_text()),
            // ureq names the URL first (the caller does already) and repeats its error
            // kind ("Network Error: Network Error: ..."): each part once.
            other => {
                let text = other.to_string();
                let text = text.strip_prefix(&format!("{url}: ")).unwrap_or(&text).replace(url, &shown(Path::new(url)));
                let mut parts: Vec<&str> = text.split(": ").collect();
                parts.dedup();
                parts.join(": ")
            }
        })?;
        if response.status() != 206 {
            return Err(format!(
                "the server answered {} {} to a range request: it does not serve byte ranges",
                response.status(),
                response.status_text()
            ));
        }
        Ok(response)
    }

    fn read_at(&self, buf: &mut [u8], offset: u64) -> Result<(), String> {
        if buf.is_empty() {
            return Ok(());
        }
        let last = offset + buf.len() as u64 - 1;
        let response = Self::get(&self.agent, &self.url, offset, last)?;
        match content_range(&response) {
            Some((a, b, total)) if a == offset && b == last && total.is_none_or(|t| t == self.len) => {}
            Some((_, _, Some(total))) if total != self.len => {
                return Err(format!(
                    "bytes {offset}..={last}: the archive changed on the server ({total} bytes, {} when opened)",
                    self.len
                ))
            }
            _ => {
                return Err(format!(
                    "bytes {offset}..={last}: the server sent another range ({})",
                    response.header("Content-Range").unwrap_or("no Content-Range")
                ))
            }
        }
        if let Some(coding) = response.header("Content-Encoding").filter(|c| !c.trim().eq_ignore_ascii_case("identity"))
        {
            return Err(format!(
                "bytes {offset}..={last}: the server sent them encoded ({coding}) although asked for identity"
            ));
        }
        let mut reader = response.into_reader();
        std::io::Read::read_exact(&mut reader, buf)
            .map_err(|e| format!("bytes {offset}..={last}: {e} (the server sent fewer bytes than asked)"))
    }
}

/// `Content-Range: bytes FIRST-LAST/TOTAL` (TOTAL may be `*`, unknown).
fn content_range(response: &ureq::Response) -> Option<(u64, u64, Option<u64>)> {
    let value = response.header("Content-Range")?.trim();
    let (range, total) = value.strip_prefix("bytes ")?.split_once('/')?;
    let (first, last) = range.split_once('-')?;
    let total = match total.trim() {
        "*" => None,
        t => Some(t.parse().ok()?),
    };
    Some((first.trim().parse().ok()?, last.trim().parse().ok()?, total))
}

#[cfg(test)]
mod tests {
    use crate::input::archive::bytes::shown;
    use std::path::Path;

    #[test]
    fn credentials_are_hidden_and_nothing_else_changes() {
        for (given, expected) in [
            ("https://user:pw@host.example/t.pmtiles", "https://***@host.example/t.pmtiles"),
            ("HTTP://pw@127.0.0.1:8080/a?b=c", "HTTP://***@127.0.0.1:8080/a?b=c"),
            ("https://a:b@c@host/x", "https://***@host/x"),
            ("https://host/user@x.pmtiles", "https://host/user@x.pmtiles"),
            ("https://host?mail=a@b", "https://host?mail=a@b"),
            ("http://host", "http://host"),
            ("/data/me@work/t.pmtiles", "/data/me@work/t.pmtiles"),
        ] {
            assert_eq!(shown(Path::new(given)), expected, "{given}");
        }
    }
}
