//! Panics from libraries that should have returned an error.

/// Runs `f` (a third-party parser) with the panic message kept off standard error, turning a
/// panic into `Err(its message)`: for libraries that panic on malformed input where they should
/// return an error. The process's panic hook is swapped for the call (callers are loaders that
/// run before any worker threads).
pub fn quietly<T>(f: impl FnOnce() -> T) -> std::result::Result<T, String> {
    static HOOK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one_at_a_time = HOOK.lock().unwrap_or_else(|e| e.into_inner());
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    std::panic::set_hook(previous);
    r.map_err(|e| panic_message(&*e))
}

/// The text a panic was raised with.
pub fn panic_message(e: &(dyn std::any::Any + Send)) -> String {
    e.downcast_ref::<String>()
        .cloned()
        .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "unknown panic".into())
}
