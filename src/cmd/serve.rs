//! `chatsplat serve`: chat with a trained scene in the browser (the `viewer` crate).

use super::SceneArgs;
use std::net::SocketAddr;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Address to listen on. Loopback by default: another address makes the scene and the model
    /// reachable from other machines, without authentication.
    #[arg(long, default_value = "127.0.0.1:7860")]
    pub addr: SocketAddr,
    /// Questions that may wait for the model; more are refused (HTTP 503) until one is answered.
    #[arg(long, default_value_t = 8)]
    pub queue: usize,
    /// Default answer length in tokens (a request may ask for another, up to 1024).
    #[arg(long, default_value_t = 256)]
    pub max_new_tokens: usize,
    /// Let pages of this origin (e.g. http://localhost:3000) call the API; repeatable. Other
    /// origins are refused.
    #[arg(long)]
    pub allow_origin: Vec<String>,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if a.queue == 0 {
        anyhow::bail!("--queue must be at least 1");
    }
    if !a.addr.ip().is_loopback() {
        eprintln!(
            "warning: listening on {}: the scene and the model are reachable from other machines, with no \
             authentication",
            a.addr
        );
    }
    let opts = viewer::ServeOptions {
        addr: a.addr,
        run: a.scene.run.clone(),
        language: a.scene.language.clone(),
        vlm: a.scene.vlm_dir()?,
        backend: a.scene.backend,
        queue: a.queue,
        max_new_tokens: a.max_new_tokens,
        allow_origins: a.allow_origin,
    };
    viewer::serve(opts, |p| match p {
        viewer::Progress::Loading(addr) => eprintln!("listening on {addr}; loading {}", a.scene.run.display()),
        viewer::Progress::Warning(w) => eprintln!("warning: {w}"),
        viewer::Progress::Ready { addr, gaussians, views, seconds } => {
            eprintln!("loaded {gaussians} Gaussians, {views} views and the model in {seconds:.1} s; Ctrl-C stops");
            // stdout carries the one line a script needs: the URL
            println!("chatsplat viewer: http://{addr}/");
        }
    })?;
    eprintln!("stopped");
    Ok(())
}
