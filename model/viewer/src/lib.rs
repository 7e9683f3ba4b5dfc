//! `chatsplat serve`: chat with a trained scene in the browser. One process holds one
//! [`ChatSession`](model::chat::ChatSession) on one inference thread ([`engine`]) and serves:
//!
//! * the page ([`assets`], embedded: no network needed): the scene drawn by Spark over three.js
//!   (WebGL2), or by chatsplat's own rasterizer (`?render=server`, or where WebGL2 is missing),
//!   orbit and WASD fly, training cameras to jump to; a click picks the object under the pointer
//!   (the server renders the identity at exactly the page's camera) and tints it red; a chat box
//!   with three scopes: this view (any camera), the picked object, the whole scene;
//! * the JSON API under it ([`routes`]), whose camera contract is [`camera`].
//!
//! Data flow: page camera -> [`camera::ViewCamera::to_camera`] -> `ChatSession::click` /
//! `view_tokens` / `view_image` -> answer tokens streamed back as server-sent events.

pub mod assets;
pub mod camera;
pub mod conversations;
pub mod engine;
pub mod error;
pub mod routes;
pub mod scene_info;
pub mod splat_files;

use engine::{Engine, Queues};
use model::chat::ChatSession;
use model::run::GeometryRun;
use model::{Backend, Error, Result};
use routes::AppState;
use scene_info::{ObjectNames, SceneInfo};
use splat_files::SplatFiles;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

/// How to serve.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    pub addr: SocketAddr,
    /// The geometry run (with its language run).
    pub run: PathBuf,
    /// The language run (default: RUN/language).
    pub language: Option<PathBuf>,
    pub vlm: PathBuf,
    pub backend: Backend,
    /// Questions that may wait (the one being answered not counted); more are refused (503).
    pub queue: usize,
    /// Default answer length in tokens.
    pub max_new_tokens: usize,
    /// Origins (`http://host:port`) allowed to call the API from their pages.
    pub allow_origins: Vec<String>,
}

/// What `serve` reports as it starts.
pub enum Progress<'a> {
    /// Listening (the port is taken), loading the scene and the model.
    Loading(&'a SocketAddr),
    /// Loaded; notes about the scene (e.g. object names unavailable).
    Warning(&'a str),
    /// Ready at this address, with this many Gaussians and views.
    Ready { addr: &'a SocketAddr, gaussians: usize, views: usize, seconds: f64 },
}

/// Serves the scene until Ctrl-C (or SIGTERM); then stops taking requests, ends the answer in
/// progress at its next token and returns.
pub fn serve(opts: ServeOptions, mut progress: impl FnMut(Progress)) -> Result<()> {
    let t0 = std::time::Instant::now();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| Error::input(format!("cannot start the server's runtime: {e}")))?;
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind(opts.addr))
        .map_err(|e| Error::input(format!("cannot listen on {}: {e}", opts.addr)))?;
    let addr = listener.local_addr().map_err(|e| Error::input(format!("cannot listen on {}: {e}", opts.addr)))?;
    progress(Progress::Loading(&addr));

    // The inference thread opens the session itself: the model never crosses threads.
    let queues = Queues::new(opts.queue, 64);
    let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<Served>>();
    let worker = {
        let (opts, queues) = (opts.clone(), queues.clone());
        std::thread::Builder::new()
            .name("chatsplat-inference".into())
            .spawn(move || {
                let loaded = model::catch_backend("loading", || load(&opts)).and_then(|r| r);
                match loaded {
                    Ok((engine, served)) => {
                        let _ = ready_tx.send(Ok(served));
                        engine.run(&queues);
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                }
            })
            .map_err(|e| Error::input(format!("cannot start the inference thread: {e}")))?
    };
    let loaded = ready_rx.recv().unwrap_or_else(|_| Err(Error::input("the inference thread stopped while loading")));
    let served = match loaded {
        Ok(l) => l,
        Err(e) => {
            let _ = worker.join();
            return Err(e);
        }
    };
    for w in &served.warnings {
        progress(Progress::Warning(w));
    }
    progress(Progress::Ready {
        addr: &addr,
        gaussians: served.gaussians,
        views: served.views,
        seconds: t0.elapsed().as_secs_f64(),
    });
    let state = Arc::new(AppState {
        queues: queues.clone(),
        scene: served.scene.into(),
        splats: served.splats,
        names: served.names,
        max_new_tokens: opts.max_new_tokens,
        allow_origins: opts.allow_origins.clone(),
    });
    let app = routes::router(state);
    let stop = queues.clone();
    let result = runtime.block_on(async move {
        axum::serve(listener, app)
            .with_graceful_shutdown(async move {
                shutdown_signal().await;
                // answers in progress end at their next token, so their streams finish
                stop.close();
            })
            .await
    });
    queues.close();
    let _ = worker.join();
    result.map_err(|e| Error::input(format!("the server failed: {e}")))
}

/// What the HTTP side serves from the loaded scene.
struct Served {
    /// `GET /api/scene`; the splat files, and the object names they are saved under.
    scene: Vec<u8>,
    splats: Arc<SplatFiles>,
    names: ObjectNames,
    warnings: Vec<String>,
    gaussians: usize,
    views: usize,
}

fn load(opts: &ServeOptions) -> Result<(Engine, Served)> {
    let run = GeometryRun::new(&opts.run);
    let session = ChatSession::open(&run, opts.language.as_deref(), &opts.vlm, &opts.backend.device()?)?;
    session.check_max_new_tokens("--max-new-tokens", opts.max_new_tokens)?;
    let mut warnings = Vec::new();
    let names = ObjectNames::of_run(&run, &mut warnings);
    if !session.scene.masks {
        warnings.push("the scene was trained without instance masks: clicking objects is off".into());
    }
    if let Some(note) = &session.model_note {
        warnings.push(note.clone());
    }
    let model_name = opts.vlm.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mut info = SceneInfo::new(&session, &run, &names, model_name, opts.backend.to_string(), opts.max_new_tokens)?;
    let files = Arc::new(SplatFiles::of(&session));
    info.splat_bytes = files.sizes();
    let served = Served {
        scene: serde_json::to_vec(&info).map_err(|e| Error::input(format!("scene info: {e}")))?,
        splats: files.clone(),
        names: names.clone(),
        warnings,
        gaussians: info.gaussians,
        views: info.views.len(),
    };
    Ok((Engine::new(session, names, files), served))
}

async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
