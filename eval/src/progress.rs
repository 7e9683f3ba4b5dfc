//! A progress bar on stderr (indicatif): `label [#####     ] done/total unit, rate, eta, extra`.
//! Hidden automatically when stderr is not a terminal.

/// A progress bar.
pub struct Progress {
    bar: indicatif::ProgressBar,
}

impl Progress {
    pub fn new(label: impl Into<String>, unit: &'static str) -> Self {
        let bar = indicatif::ProgressBar::new(1);
        let style = indicatif::ProgressStyle::with_template(&format!(
            "{{prefix}} [{{bar:30}}] {{pos}}/{{len}} {unit} ({{per_sec}}, eta {{eta}}) {{msg}}"
        ))
        .expect("valid template")
        .progress_chars("#> ");
        bar.set_style(style);
        bar.set_prefix(label.into());
        Self { bar }
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
    }
}
