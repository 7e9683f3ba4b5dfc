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

/// An `--allow-origin` is one origin as a browser sends it (`scheme://host[:port]`): a wildcard
/// would open the model to every page the user visits, and a path or a trailing slash would never
/// match, so both are refused.
fn check_origin(o: &str) -> anyhow::Result<()> {
    if o.contains('*') {
        anyhow::bail!(
            "--allow-origin {o}: a wildcard would let every web page you visit use this scene and model; name each \
             origin (e.g. --allow-origin http://localhost:3000)"
        );
    }
    let rest = o.strip_prefix("http://").or_else(|| o.strip_prefix("https://"));
    match rest {
        Some(host) if !host.is_empty() && !host.contains('/') && !host.contains(char::is_whitespace) => Ok(()),
        _ => anyhow::bail!(
            "--allow-origin {o}: expected an origin as browsers send it, scheme://host[:port] with no path or \
             trailing slash (e.g. http://localhost:3000)"
        ),
    }
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if a.queue == 0 {
        anyhow::bail!("--queue must be at least 1");
    }
    for o in &a.allow_origin {
        check_origin(o)?;
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
