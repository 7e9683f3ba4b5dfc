//! What the app shows while a scene trains: a progress bar per stage and each stage's summary
//! line. `train`, `extract` and `train-language` show their one stage through it, the demo and
//! `batch` the whole [`train::pipeline`]; so every command prints the same lines.

use model::Backend;
use model::data::Dataset;
use model::run::{GeometryRun, LanguageRun, TeacherDir};
use scoring::progress::Progress;
use std::path::Path;
use std::time::Instant;
use train::geometry::{self, RunSummary};
use train::language::{LangProgress, LangSummary, LanguageTrainConfig};
use train::pipeline::{Observer, Stage};
use train::teacher::{ExtractOptions, ExtractSummary, Plan};

/// A progress bar per stage on stderr and the summary lines on stdout.
pub struct Bars {
    backend: Backend,
    bar: Option<Progress>,
    /// When the geometry bar last moved (it moves at most four times a second).
    last: Instant,
    /// Called as each stage starts (the demo's step headings).
    heading: Box<dyn FnMut(Stage)>,
}

impl Bars {
    pub fn new(backend: Backend) -> Self {
        Self { backend, bar: None, last: Instant::now(), heading: Box::new(|_| {}) }
    }

    /// As [`new`](Self::new), calling `heading` as each stage starts.
    pub fn with_heading(backend: Backend, heading: impl FnMut(Stage) + 'static) -> Self {
        Self { heading: Box::new(heading), ..Self::new(backend) }
    }
}

impl Observer for Bars {
    fn start(&mut self, stage: Stage, _resumed_from: Option<usize>) {
        (self.heading)(stage);
        let (label, unit) = match stage {
            Stage::Geometry => ("train", "it"),
            Stage::Objects => ("identity", "it"),
            Stage::Teacher => ("extract", "views"),
            Stage::Language => ("language", "it"),
        };
        self.bar = Some(Progress::new(label, unit));
    }

    fn dataset(&mut self, data: &Path, ds: &Dataset) {
        let cam = &ds.train[0].camera;
        eprintln!(
            "{}: {} training / {} held-out views of {}x{}",
            data.display(),
            ds.train.len(),
            ds.test.len(),
            cam.width,
            cam.height
        );
    }

    fn geometry(&mut self, p: &geometry::Progress) {
        if let Some(bar) = &self.bar
            && (self.last.elapsed().as_millis() > 250 || p.iter == p.iters)
        {
            bar.update_with(p.iter, p.iters, &format!("loss {:.4} psnr {:.2} N {}", p.loss, p.psnr, p.gaussians));
            self.last = Instant::now();
        }
    }

    fn geometry_done(&mut self, s: &RunSummary, out: &GeometryRun) {
        if let Some(at) = s.resumed_from {
            println!("resumed from iteration {at}");
        }
        println!(
            "{} Gaussians; {} views: PSNR {:.2} dB, SSIM {:.4}{}; {:.3} s/iter on {} -> {}",
            s.gaussians,
            s.eval.views,
            s.eval.psnr,
            s.eval.ssim,
            s.eval.miou.map(|m| format!(", identity mIoU {m:.3}")).unwrap_or_default(),
            s.seconds_per_iter,
            self.backend,
            out.dir.display()
        );
    }

    fn identity(&mut self, iter: usize, iters: usize, loss: f32) {
        if let Some(bar) = &self.bar
            && (self.last.elapsed().as_millis() > 250 || iter == iters)
        {
            bar.update_with(iter, iters, &format!("cross-entropy {loss:.4}"));
            self.last = Instant::now();
        }
    }

    fn objects_done(
        &mut self,
        m: &train::masks::files::Summary,
        i: &train::masks::identity_run::IdentitySummary,
        out: &GeometryRun,
    ) {
        println!(
            "per-view masks matched: {} objects over {} views ({:.0} ms per view); identity: {} of {} Gaussians in \
             objects, cross-entropy {:.4} -> {:.4} -> {}",
            m.objects.len(),
            m.views,
            m.per_view_ms,
            i.object_gaussians,
            i.gaussians,
            i.first_loss,
            i.last_loss,
            out.dir.display()
        );
    }

    fn teacher_plan(&mut self, plan: &Plan, opts: &ExtractOptions, out: &TeacherDir) {
        let objects: usize = plan.views.iter().map(|v| v.objects.len()).sum();
        let novel = opts.novel.as_ref().map_or(0, |n| n.count);
        let views = match novel {
            0 => format!("{} training views", plan.views.len()),
            n => format!("{} training views + {n} novel views", plan.views.len() - n),
        };
        eprintln!(
            "{views} + {objects} object crops -> {} images of {}x{} tokens; about {:.1} MB of f16 in {}",
            plan.views.len() + objects,
            plan.tokens_per_image,
            plan.dim,
            plan.bytes as f64 / 1e6,
            out.dir.display()
        );
    }

    fn teacher(&mut self, done: usize, total: usize) {
        if let Some(bar) = &self.bar {
            bar.update(done, total);
        }
    }

    fn teacher_done(&mut self, s: &ExtractSummary, seconds: f64, out: &TeacherDir) {
        let to = if s.indexed {
            out.index().display().to_string()
        } else {
            format!(
                "{} ({} of {} views done: the index waits for the other shards)",
                out.dir.display(),
                s.views_done,
                s.views
            )
        };
        println!(
            "teacher tokens: {} view files written, {} already complete (skipped), {} images encoded in {seconds:.1} s \
                -> {to}",
            s.written, s.skipped, s.images,
        );
    }

    fn language(&mut self, p: &LangProgress) {
        if let Some(bar) = self.bar.as_ref().filter(|_| p.iter.is_multiple_of(5) || p.iter == p.iters) {
            let s = p.step;
            let msg = format!("loss {:.4} view {:.4} obj {:.4} ({})", s.loss, s.view_l1, s.object_l1, s.objects);
            bar.update_with(p.iter, p.iters, &msg);
        }
    }

    fn language_done(&mut self, s: &LangSummary, cfg: &LanguageTrainConfig, out: &LanguageRun) {
        if let Some(at) = s.resumed_from {
            eprintln!("resumed from iteration {at}");
        }
        println!(
            "token L1 on training views: view {:.4} -> {:.4}, object {:.4} -> {:.4}; {:.3} s/iter; {} of {} \
                Gaussians reached a language map -> {}",
            s.before.0,
            s.after.0,
            s.before.1,
            s.after.1,
            s.seconds_per_iter,
            s.gaussians_used,
            s.gaussians,
            out.dir.display()
        );
        if let Some(c) = &s.compaction {
            println!(
                "compact: the language maps keep {} of {} Gaussians ({:.0} %); training token L1 view {:.4} -> {:.4}, \
                    object {:.4} -> {:.4} (within {} %) -> {}",
                c.kept.len(),
                c.gaussians,
                100.0 * c.kept.len() as f64 / c.gaussians.max(1) as f64,
                c.token_l1_full.0,
                c.token_l1_kept.0,
                c.token_l1_full.1,
                c.token_l1_kept.1,
                100.0 * c.tolerance,
                out.compaction().display()
            );
        } else if cfg.compact_tolerance > 0.0 {
            println!(
                "compact: no fraction of the Gaussians down to half kept the training views' token L1 within {} %: \
                    every Gaussian kept",
                100.0 * cfg.compact_tolerance
            );
        }
    }
}
