//! A progress bar on stderr (indicatif): `label [#####     ] done/total unit, rate, eta, extra`.
//! When stderr is not a terminal (a log file, CI), a plain line every 30 seconds and at the end
//! instead, so that long runs under `nohup` still show where they are. Also the peak memory a run
//! reports ([`peak_rss_gib`]).

use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How often the plain-line form prints.
const LOG_EVERY: Duration = Duration::from_secs(30);

/// A progress bar.
pub struct Progress {
    bar: indicatif::ProgressBar,
    label: String,
    unit: &'static str,
    /// Plain lines (stderr is not a terminal): the start, the last line's time, and the count
    /// the bar started from (a resumed run's first update is its first step done here).
    log: Option<Mutex<(Instant, Instant, Option<usize>)>>,
}

impl Progress {
    pub fn new(label: impl Into<String>, unit: &'static str) -> Self {
        let label = label.into();
        let bar = indicatif::ProgressBar::new(1);
        let style = indicatif::ProgressStyle::with_template(&format!(
            "{{prefix}} [{{bar:30}}] {{pos}}/{{len}} {unit} ({{per_sec}}, eta {{eta}}) {{msg}}"
        ))
        .expect("valid template")
        .progress_chars("#> ");
        bar.set_style(style);
        bar.set_prefix(label.clone());
        let now = Instant::now();
        let log = (!std::io::stderr().is_terminal()).then(|| Mutex::new((now, now, None)));
        Self { bar, label, unit, log }
    }

    /// Starts over under a new label (the next stage of a run): count, rate and eta from zero.
    pub fn restart(&mut self, label: impl Into<String>) {
        self.label = label.into();
        self.bar.reset();
        self.bar.set_prefix(self.label.clone());
        if let Some(log) = &mut self.log {
            let now = Instant::now();
            *log.get_mut().unwrap_or_else(|e| e.into_inner()) = (now, now, None);
        }
    }

    pub fn update(&self, done: usize, total: usize) {
        self.update_with(done, total, "");
    }

    /// As [`update`](Self::update), with extra text (loss, PSNR...) after the counts.
    pub fn update_with(&self, done: usize, total: usize, extra: &str) {
        self.bar.set_length(total.max(1) as u64);
        self.bar.set_position(done as u64);
        self.bar.set_message(extra.to_string());
        if done >= total {
            self.bar.finish();
        }
        if let Some(log) = &self.log {
            let mut times = log.lock().unwrap_or_else(|e| e.into_inner());
            let now = Instant::now();
            let from = *times.2.get_or_insert(done.saturating_sub(1));
            if now - times.1 >= LOG_EVERY || (done >= total && done > 0) {
                times.1 = now;
                eprintln!("{}", plain_line(&self.label, self.unit, done, total, from, now - times.0, extra));
            }
        }
    }
}

/// This process's peak resident memory so far in GiB (Linux `VmHWM`; `None` elsewhere): what the
/// app and the benchmarks report beside their timings.
pub fn peak_rss_gib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / (1u64 << 20) as f64)
}

/// `label: done/total unit (rate unit/s, eta) extra`.
/// One plain progress line; the rate counts what was done since `from` (where a resumed run's
/// bar started), not the steps done before.
fn plain_line(
    label: &str,
    unit: &str,
    done: usize,
    total: usize,
    from: usize,
    elapsed: Duration,
    extra: &str,
) -> String {
    let secs = elapsed.as_secs_f64();
    let rate = if secs > 0.0 { done.saturating_sub(from) as f64 / secs } else { 0.0 };
    let eta =
        if rate > 0.0 && total > done { format!(", eta {:.0} s", (total - done) as f64 / rate) } else { String::new() };
    format!("{label}: {done}/{total} {unit} ({rate:.2} {unit}/s{eta}) {extra}").trim_end().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_line_reports_rate_and_eta() {
        let l = plain_line("train", "iters", 30, 90, 0, Duration::from_secs(60), "loss 0.5");
        assert_eq!(l, "train: 30/90 iters (0.50 iters/s, eta 120 s) loss 0.5");
        assert_eq!(plain_line("x", "steps", 5, 5, 0, Duration::from_secs(2), ""), "x: 5/5 steps (2.50 steps/s)");
        // resumed at step 1,000: 30 steps in 60 s is 0.5 steps/s, not 17
        let l = plain_line("train", "steps", 1030, 3000, 1000, Duration::from_secs(60), "");
        assert_eq!(l, "train: 1030/3000 steps (0.50 steps/s, eta 3940 s)");
    }
}
