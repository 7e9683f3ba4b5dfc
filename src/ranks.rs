//! Which processes this run is: one, or the ranks of an MPI job (`mpirun -np N`, Slurm's `srun`,
//! a Kubeflow MPIJob) for the data-parallel trainers. MPI is behind the `mpi` feature; a build
//! without it refuses to run under a launcher with several ranks (every rank would train alone
//! and write the same files).

use train::dist::{Collective, Solo};

/// The rank count the launcher gave this process, from the variables OpenMPI, MPICH/Hydra, PMIx
/// and Slurm set (`None` when not launched by one).
fn launched_ranks() -> Option<usize> {
    let var = |v: &str| std::env::var(v).ok().and_then(|s| s.trim().parse::<usize>().ok());
    let under_pmi = std::env::var_os("PMIX_RANK").is_some() || std::env::var_os("PMI_RANK").is_some();
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE"].iter().find_map(|v| var(v)).or_else(|| {
        // Slurm's srun --mpi=pmix sets the rank, and the task count in its own variables
        under_pmi.then(|| var("SLURM_STEP_NUM_TASKS").or_else(|| var("SLURM_NTASKS"))).flatten()
    })
}

/// The ranks this process belongs to.
pub enum Ranks {
    Solo,
    #[cfg(feature = "mpi")]
    Mpi(mpi_ranks::Mpi),
}

impl Ranks {
    /// Joins the job the launcher started, if any. `data_parallel`: the command can run on several
    /// ranks (else several ranks are refused, naming the command).
    pub fn join(command: &str, data_parallel: bool) -> anyhow::Result<Self> {
        let n = match launched_ranks() {
            Some(n) if n > 1 => n,
            _ => return Ok(Ranks::Solo),
        };
        if !data_parallel {
            anyhow::bail!(
                "`chatsplat {command}` was launched on {n} ranks, but it runs on one process: only train-vlm and \
                 train-language are data-parallel (run {command} without mpirun)"
            );
        }
        #[cfg(feature = "mpi")]
        {
            Ok(Ranks::Mpi(mpi_ranks::Mpi::init(n)?))
        }
        #[cfg(not(feature = "mpi"))]
        {
            anyhow::bail!(
                "launched on {n} ranks, but this chatsplat was built without MPI: every rank would train alone and \
                 write the same files. Build it with `cargo build --release --features mpi` (needs Debian's \
                 libopenmpi-dev and libclang-dev)"
            )
        }
    }

    /// The collective the trainers use.
    pub fn collective(&self) -> &dyn Collective {
        match self {
            Ranks::Solo => &Solo,
            #[cfg(feature = "mpi")]
            Ranks::Mpi(m) => m,
        }
    }

    /// Reports an error and ends the process; on several ranks it prefixes the rank and stops
    /// every other rank too (MPI_Abort), so none waits for this one.
    pub fn fail(&self, e: &anyhow::Error) -> std::process::ExitCode {
        match self {
            Ranks::Solo => {
                eprintln!("error: {}", message(e));
                std::process::ExitCode::FAILURE
            }
            #[cfg(feature = "mpi")]
            Ranks::Mpi(m) => m.abort(&message(e)),
        }
    }

    /// After a data-parallel run: this rank's time inside collectives and its peak memory, one
    /// line on standard error (every rank prints its own).
    pub fn report(&self, seconds: f64) {
        #[cfg(feature = "mpi")]
        if let Ranks::Mpi(m) = self {
            let (total, by) = m.waited();
            let share = |d: std::time::Duration| 100.0 * d.as_secs_f64() / seconds.max(1e-9);
            let parts: Vec<String> =
                by.iter().take(3).map(|(what, d)| format!("{what} {:.1} s", d.as_secs_f64())).collect();
            let peak = scoring::progress::peak_rss_gib().map_or(String::new(), |g| format!("; peak memory {g:.2} GiB"));
            say(&format!(
                "rank {} of {}: {:.1} s in collectives ({:.1} % of {seconds:.1} s: {}){peak}",
                m.rank(),
                m.size(),
                total.as_secs_f64(),
                share(total),
                parts.join(", ")
            ));
        }
        let _ = seconds;
    }
}

/// One line on standard error in a single write: `eprintln!` writes its pieces one by one, so
/// the lines of two ranks that share mpirun's standard error could interleave mid-line.
#[cfg(feature = "mpi")]
fn say(line: &str) {
    use std::io::Write;
    let _ = std::io::stderr().lock().write_all(format!("{line}\n").as_bytes());
}

#[cfg(feature = "mpi")]
mod mpi_ranks {
    use model::error::{Error, Result};
    use mpi::collective::SystemOperation;
    use mpi::datatype::Equivalence;
    use mpi::request::{Request, Scope};
    use mpi::traits::*;
    use std::cell::RefCell;
    use std::collections::BTreeMap;
    use std::time::{Duration, Instant};
    use train::dist::Collective;

    /// How long a rank waits in one collective before it decides another rank is gone
    /// (`CHATSPLAT_MPI_TIMEOUT`, seconds); rank 0 evaluates and writes checkpoints while the
    /// others wait, so it is generous.
    const TIMEOUT_S: u64 = 600;

    /// The ranks of an MPI job.
    pub struct Mpi {
        _universe: mpi::environment::Universe,
        world: mpi::topology::SimpleCommunicator,
        rank: usize,
        size: usize,
        timeout: Duration,
        /// Time inside each kind of collective (by `what`).
        waited: RefCell<BTreeMap<String, Duration>>,
    }

    impl Mpi {
        /// Initialises MPI (only the main thread calls it); the launcher said `n` ranks.
        pub fn init(n: usize) -> anyhow::Result<Self> {
            let timeout = match std::env::var("CHATSPLAT_MPI_TIMEOUT") {
                Ok(s) => match s.trim().parse::<u64>() {
                    Ok(t) if t > 0 => Duration::from_secs(t),
                    _ => anyhow::bail!("CHATSPLAT_MPI_TIMEOUT: `{s}` is not a positive number of seconds"),
                },
                Err(_) => Duration::from_secs(TIMEOUT_S),
            };
            let (universe, _) = mpi::initialize_with_threading(mpi::Threading::Funneled)
                .ok_or_else(|| anyhow::anyhow!("MPI could not be initialised (already initialised?)"))?;
            let world = universe.world();
            let (rank, size) = (world.rank() as usize, world.size() as usize);
            if size != n {
                anyhow::bail!("the launcher said {n} ranks but MPI's world has {size}");
            }
            share_cores(size);
            Ok(Self { _universe: universe, world, rank, size, timeout, waited: RefCell::default() })
        }

        /// Time spent inside collectives so far, in all and by kind (largest first).
        pub fn waited(&self) -> (Duration, Vec<(String, Duration)>) {
            let w = self.waited.borrow();
            let mut by: Vec<(String, Duration)> = w.iter().map(|(k, v)| (k.clone(), *v)).collect();
            by.sort_by_key(|e| std::cmp::Reverse(e.1));
            (w.values().sum(), by)
        }

        /// Prints `message` with this rank and stops the whole job.
        pub fn abort(&self, message: &str) -> ! {
            super::say(&format!("error (rank {} of {}): {message}; stopping every rank", self.rank, self.size));
            self.world.abort(1)
        }

        /// `buf` reduced element-wise over the ranks by `op`, in place.
        fn all_reduce<T: Equivalence + Clone>(&self, what: &str, buf: &mut [T], op: SystemOperation) {
            let send = buf.to_vec();
            mpi::request::scope(|scope| {
                let req = self.world.immediate_all_reduce_into(scope, &send[..], buf, op);
                self.finish(what, req)
            });
        }

        /// Completes `req`, polling: OpenMPI progresses a non-blocking collective only inside
        /// `MPI_Test`, so the first second spins on it (a step's all-reduce, waits included,
        /// finishes within it), then short sleeps leave the core to others (rank 0 evaluating or
        /// writing); past the timeout the job is stopped.
        fn finish<'a, D: ?Sized, S: Scope<'a>>(&self, what: &str, mut req: Request<'a, D, S>) {
            let t0 = Instant::now();
            loop {
                match req.test() {
                    Ok(_) => break,
                    Err(r) => req = r,
                }
                let waited = t0.elapsed();
                if waited > self.timeout {
                    self.abort(&format!(
                        "no answer from the other ranks in {:.0} s during {what}: a rank has stopped or hangs \
                         (CHATSPLAT_MPI_TIMEOUT sets the limit)",
                        waited.as_secs_f64()
                    ));
                }
                if waited < Duration::from_secs(1) {
                    std::hint::spin_loop();
                } else {
                    std::thread::sleep(Duration::from_micros(200));
                }
            }
            *self.waited.borrow_mut().entry(what.to_string()).or_default() += t0.elapsed();
        }
    }

    /// Gives each rank of a machine its share of the cores for burn's threads (unless
    /// `RAYON_NUM_THREADS` says otherwise).
    fn share_cores(size: usize) {
        if std::env::var_os("RAYON_NUM_THREADS").is_some() {
            return;
        }
        let local = ["OMPI_COMM_WORLD_LOCAL_SIZE", "MPI_LOCALNRANKS"]
            .iter()
            .find_map(|v| std::env::var(v).ok()?.trim().parse::<usize>().ok())
            .unwrap_or(size);
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let _ = rayon::ThreadPoolBuilder::new().num_threads((cores / local.max(1)).max(1)).build_global();
    }

    impl Collective for Mpi {
        fn rank(&self) -> usize {
            self.rank
        }
        fn size(&self) -> usize {
            self.size
        }
        fn sum_f32(&self, what: &str, buf: &mut [f32]) -> Result<()> {
            self.all_reduce(what, buf, SystemOperation::sum());
            Ok(())
        }
        fn sum_f64(&self, what: &str, buf: &mut [f64]) -> Result<()> {
            self.all_reduce(what, buf, SystemOperation::sum());
            Ok(())
        }
        fn broadcast_f32(&self, what: &str, buf: &mut [f32]) -> Result<()> {
            let mut len = [buf.len() as u64];
            mpi::request::scope(|scope| {
                let req = self.world.process_at_rank(0).immediate_broadcast_into(scope, &mut len[..]);
                self.finish(what, req)
            });
            if len[0] != buf.len() as u64 {
                return Err(Error::input(format!(
                    "data-parallel training: rank 0 has {} weights, rank {} has {}: the ranks must run the same \
                     build and configuration",
                    len[0],
                    self.rank,
                    buf.len()
                )));
            }
            mpi::request::scope(|scope| {
                let req = self.world.process_at_rank(0).immediate_broadcast_into(scope, buf);
                self.finish(what, req)
            });
            Ok(())
        }
        fn min_max(&self, what: &str, value: u64) -> Result<(u64, u64)> {
            let mut got = [value, u64::MAX - value];
            self.all_reduce(what, &mut got, SystemOperation::max());
            Ok((u64::MAX - got[1], got[0]))
        }
    }
}

/// An error and its causes on one line, each cause once: the library errors already print their
/// source (`path: cannot read: No such file`), which `{:#}` would repeat.
fn message(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let c = cause.to_string();
        if !text.contains(&c) {
            text.push_str(": ");
            text.push_str(&c);
        }
    }
    text
}
