//! The window's event loop, one for both viewers (in memory, `viewer.rs`; streamed,
//! `stream_view.rs`): the panel sees each event first, then the camera's controls, then
//! the window itself (close, resize, hidden, redraw). `--frames`, `--screenshot` and
//! `--resize-at` are served here, and nothing is drawn while the window is minimized or
//! hidden.

use crate::app::controls::{Controller, Input};
use crate::app::hud::Hud;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow};
use winit::keyboard::KeyCode;
use winit::window::{Window, WindowId};

/// What the loop keeps of the window, and the scripted run's options.
pub struct WindowState {
    pub window: Option<Arc<Window>>,
    /// The swapchain is made again before the next frame (resized, suboptimal).
    pub swapchain_dirty: bool,
    pub minimized: bool,
    /// Fully hidden (winit's Occluded).
    pub occluded: bool,
    /// Set by Ctrl-C: the viewer closes as if its window were closed, so that the trace
    /// and the recorded flight are written.
    pub interrupted: Arc<AtomicBool>,
    /// The first error (opening, a frame); the loop exits with it.
    pub error: Option<anyhow::Error>,
    /// `--frames`: close after this many frames.
    pub frames: Option<u64>,
    /// `--screenshot`: where the last of those frames is saved.
    pub screenshot: Option<PathBuf>,
    /// `--resize-at`: before frame `.0`, ask for a window of `.1 x .2`.
    pub resizes: Vec<(u64, u32, u32)>,
    /// Where the next frame drawn is saved (P, `--screenshot`).
    pub screenshot_next: Option<PathBuf>,
    /// The last cursor position in the window (drag-to-look).
    pub cursor: Option<(f32, f32)>,
}

impl WindowState {
    pub fn new(
        interrupted: Arc<AtomicBool>,
        frames: Option<u64>,
        screenshot: Option<PathBuf>,
        resizes: Vec<(u64, u32, u32)>,
    ) -> Self {
        WindowState {
            window: None,
            swapchain_dirty: false,
            minimized: false,
            occluded: false,
            interrupted,
            error: None,
            frames,
            screenshot,
            resizes,
            screenshot_next: None,
            cursor: None,
        }
    }

    /// Minimized or hidden: no frame is drawn.
    pub fn hidden(&self) -> bool {
        self.minimized || self.occluded
    }

    pub(crate) fn fail(&mut self, event_loop: &ActiveEventLoop, e: anyhow::Error) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        event_loop.exit();
    }
}

/// A viewer, as the loop drives it.
pub trait WindowApp {
    fn window_state(&mut self) -> &mut WindowState;
    /// The panel, once the window and the GPU are open.
    fn hud(&mut self) -> Option<&mut Hud>;
    /// Opens them (at the first `resumed`) and sets `window_state().window`.
    fn open(&mut self, event_loop: &ActiveEventLoop) -> anyhow::Result<()>;
    /// The camera's controller and the window's state.
    fn camera_controls(&mut self) -> (&mut Controller, &mut WindowState);
    fn key(&mut self, code: KeyCode, event_loop: &ActiveEventLoop);
    /// The mouse turned the camera by `turned` radians.
    fn turned(&mut self, turned: f32);
    /// Frames drawn so far.
    fn frames_drawn(&self) -> u64;
    /// Draws one frame (the window is open and shown).
    fn draw(&mut self) -> anyhow::Result<()>;

    /// Whether the window and the GPU are open.
    fn is_open(&mut self) -> bool {
        self.hud().is_some()
    }

    /// Whether the panel takes `event` (a click on it, one of its sliders dragged): the
    /// camera does not see it then.
    fn panel_takes(&mut self, event: &WindowEvent) -> bool {
        let window = self.window_state().window.clone();
        match (self.hud(), window) {
            (Some(hud), Some(w)) => hud.takes_input(&w, event),
            _ => false,
        }
    }
}

/// Runs a [`WindowApp`] in winit's event loop.
pub struct Windowed<A>(pub A);

impl<A: WindowApp> ApplicationHandler for Windowed<A> {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        let app = &mut self.0;
        if !app.is_open() {
            if let Err(e) = app.open(event_loop) {
                app.window_state().fail(event_loop, e);
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let app = &mut self.0;
        if app.panel_takes(&event) {
            if let WindowEvent::MouseInput { state: ElementState::Released, .. } = event {
                app.camera_controls().0.looking = false;
            }
            return;
        }
        let (ctl, state) = app.camera_controls();
        match ctl.on_event(&event, &mut state.cursor) {
            Input::Pressed(code) => return app.key(code, event_loop),
            Input::Turned(turned) => return app.turned(turned),
            Input::Taken => return,
            Input::Other => {}
        }
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Occluded(hidden) => app.window_state().occluded = hidden,
            WindowEvent::Resized(size) => {
                let state = app.window_state();
                state.minimized = size.width == 0 || size.height == 0;
                state.swapchain_dirty = true;
            }
            WindowEvent::RedrawRequested => {
                if !app.is_open() || app.window_state().hidden() {
                    return; // opening failed (the loop is exiting), or nothing is shown
                }
                let frame = app.frames_drawn();
                let state = app.window_state();
                if let Some((_, w, h)) = state.resizes.iter().find(|r| r.0 == frame).copied() {
                    if let Some(win) = &state.window {
                        let _ = win.request_inner_size(PhysicalSize::new(w, h));
                    }
                }
                if state.frames.is_some_and(|n| frame + 1 >= n) && state.screenshot.is_some() {
                    state.screenshot_next = state.screenshot.clone();
                }
                if let Err(e) = app.draw() {
                    app.window_state().fail(event_loop, e);
                    return;
                }
                let drawn = app.frames_drawn();
                if app.window_state().frames.is_some_and(|n| drawn >= n) {
                    event_loop.exit();
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let state = self.0.window_state();
        if state.interrupted.load(Ordering::SeqCst) {
            event_loop.exit();
            return;
        }
        // While minimized or hidden no redraw is asked for and the loop waits for the next
        // event (the one that shows the window again) instead of polling.
        let hidden = state.hidden();
        event_loop.set_control_flow(if hidden { ControlFlow::Wait } else { ControlFlow::Poll });
        if let (Some(w), false) = (&state.window, hidden) {
            w.request_redraw();
        }
    }
}
