//! The front-ends: the command line ([`cli`], [`commands`]), the viewer and its panel
//! ([`viewer`], [`hud`], the controls both viewers share: [`controls`], the viewer of
//! archives drawn streamed: [`stream_view`]), the benchmark ([`bench`]), the quality sweep ([`quality`]), the
//! trace picture ([`timeline`]), and what they write ([`outputs`], [`export`], [`paths`]); map coordinates ([`geo`]).

pub mod bench;
pub mod cli;
pub mod commands;
pub mod controls;
pub mod export;
pub mod geo;
pub mod hud;
pub mod outputs;
pub mod paths;
pub mod prepare;
pub mod quality;
pub mod signals;
pub mod stream;
pub mod stream_view;
pub mod timeline;
pub mod viewer;
pub mod window_loop;
