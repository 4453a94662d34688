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

pub enum Bytes {
    File(File),
    Http(Http),
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
        let len = response
            .header("Content-Range")
            .and_then(|r| r.rsplit('/').next())
            .and_then(|l| l.trim().parse::<u64>().ok())
            .ok_or_else(|| {
                format!(
                    "the server answered {} without a Content-Range length: it does not serve byte ranges",
                    response.status()
                )
            })?;
        Ok(Http { agent, url: url.to_string(), len })
    }

    fn get(agent: &ureq::Agent, url: &str, first: u64, last: u64) -> Result<ureq::Response, String> {
        let response = agent.get(url).set("Range", &format!("bytes={first}-{last}")).call().map_err(|e| match e {
            ureq::Error::Status(code, r) => format!("HTTP {code} {}", r.status_text()),
            // ureq names the URL first (the caller does already) and repeats its error
            // kind ("Network Error: Network Error: ..."): each part once.
            other => {
                let text = other.to_string();
                let text = text.strip_prefix(&format!("{url}: ")).unwrap_or(&text);
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
        let mut reader = response.into_reader();
        std::io::Read::read_exact(&mut reader, buf)
            .map_err(|e| format!("bytes {offset}..={last}: {e} (the server sent fewer bytes than asked)"))
    }
}
