//! Progress reporting for long runs: indicatif bars with rate and ETA when standard error is a
//! terminal; plain, timestamped log lines otherwise (batch jobs, cluster logs, CI), so a log
//! file never fills with redraw sequences. Nothing here affects results.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::{IsTerminal, Write};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Where progress goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Bars on a terminal, lines otherwise.
    Auto,
    /// Plain lines.
    Lines,
    /// Nothing (library use, tests).
    Quiet,
}

/// Reports stages and counted steps (tiles, files).
pub struct Progress {
    mode: Mode,
    start: Instant,
    bar: Mutex<Option<ProgressBar>>,
}

impl Progress {
    pub fn new(mode: Mode) -> Self {
        let mode = match mode {
            Mode::Auto if std::io::stderr().is_terminal() => Mode::Auto,
            Mode::Auto => Mode::Lines,
            m => m,
        };
        Progress {
            mode,
            start: Instant::now(),
            bar: Mutex::new(None),
        }
    }

    fn line(&self, msg: &str) {
        match self.mode {
            Mode::Quiet => {}
            Mode::Lines => {
                let t = self.start.elapsed().as_secs_f64();
                let _ = writeln!(std::io::stderr(), "[{t:8.1} s] {msg}");
            }
            Mode::Auto => match self.bar.lock().expect("progress lock").as_ref() {
                Some(b) => b.println(msg),
                None => {
                    let _ = writeln!(std::io::stderr(), "{msg}");
                }
            },
        }
    }

    /// A stage begins (a spinner on a terminal).
    pub fn stage(&self, name: &str) {
        self.finish();
        if self.mode == Mode::Auto {
            let b = ProgressBar::new_spinner().with_style(
                ProgressStyle::with_template("{spinner} {msg} [{elapsed}]")
                    .expect("a valid template"),
            );
            b.set_message(name.to_string());
            b.enable_steady_tick(Duration::from_millis(120));
            *self.bar.lock().expect("progress lock") = Some(b);
        } else {
            self.line(name);
        }
    }

    /// A counted stage of `len` steps begins (a bar with ETA on a terminal).
    pub fn steps(&self, name: &str, len: u64) {
        self.finish();
        if self.mode == Mode::Auto {
            let b = ProgressBar::new(len).with_style(
                ProgressStyle::with_template(
                    "{prefix} [{bar:40}] {pos}/{len} {msg} [{elapsed} elapsed, ETA {eta}]",
                )
                .expect("a valid template")
                .progress_chars("=> "),
            );
            b.set_prefix(name.to_string());
            *self.bar.lock().expect("progress lock") = Some(b);
        } else {
            self.line(&format!("{name}: {len} to do"));
        }
    }

    /// One step of the current counted stage is done.
    pub fn step(&self, msg: &str) {
        match self.mode {
            Mode::Auto => {
                if let Some(b) = self.bar.lock().expect("progress lock").as_ref() {
                    b.set_message(msg.to_string());
                    b.inc(1);
                }
            }
            _ => self.line(msg),
        }
    }

    /// A transfer of `total` bytes (if known) begins at `start` (bytes, rate and ETA on a
    /// terminal; one line when not).
    pub fn bytes(&self, name: &str, total: Option<u64>, start: u64) {
        self.finish();
        if self.mode == Mode::Auto {
            let b = match total {
                Some(t) => ProgressBar::new(t),
                None => ProgressBar::new_spinner(),
            }
            .with_style(
                ProgressStyle::with_template(
                    "{prefix} [{bar:30}] {bytes}/{total_bytes} {bytes_per_sec} ETA {eta}",
                )
                .expect("a valid template")
                .progress_chars("=> "),
            );
            b.set_prefix(name.to_string());
            b.set_position(start);
            *self.bar.lock().expect("progress lock") = Some(b);
        } else {
            let size = total.map_or("unknown size".to_string(), |t| format!("{t} bytes"));
            let from = if start > 0 {
                format!(", resuming at byte {start}")
            } else {
                String::new()
            };
            self.line(&format!("downloading {name} ({size}{from})"));
        }
    }

    /// `n` more bytes of the current transfer.
    pub fn advance(&self, n: u64) {
        if let Some(b) = self.bar.lock().expect("progress lock").as_ref() {
            b.inc(n);
        }
    }

    /// A message that stays in the log.
    pub fn note(&self, msg: &str) {
        self.line(msg);
    }

    /// Close the current bar or spinner.
    pub fn finish(&self) {
        if let Some(b) = self.bar.lock().expect("progress lock").take() {
            b.finish_and_clear();
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish();
    }
}
