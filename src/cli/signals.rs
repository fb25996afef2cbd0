//! Ctrl-C and SIGTERM for `cadence print`: both are blocked in every thread (before any thread
//! starts) and taken by one thread with `sigwait`, so a print ends on its own terms: the first
//! signal asks the print to stop at the next G-code line, a second one ends the process at once.
//!
//! A blocked signal is queued even when its disposition is "ignore" (as a shell's `cmd &`
//! leaves SIGINT): Linux never discards a signal the target blocks, so `sigwait` sees it
//! either way (`tests/tests/print_ux.rs` checks this with an inherited ignored SIGINT).

pub use cadence::gcode_source::StopRequest;
use nix::sys::signal::{SigSet, Signal};

/// Exit status of a print ended by `sig` (128 + its number: 130 for SIGINT, 143 for SIGTERM).
pub fn exit_code(sig: Signal) -> u8 {
    (128 + sig as i32).clamp(0, 255) as u8
}

/// Blocks SIGINT and SIGTERM in this thread (inherited by every thread started later) and
/// starts the thread that waits for them. Call before starting any other thread.
pub fn install(stop: &StopRequest, on_first: impl Fn(Signal) + Send + 'static) -> Result<(), String> {
    let mut set = SigSet::empty();
    set.add(Signal::SIGINT);
    set.add(Signal::SIGTERM);
    set.thread_block()
        .map_err(|e| format!("blocking SIGINT/SIGTERM: {e}"))?;
    let stop = stop.clone();
    std::thread::Builder::new()
        .name("signals".to_string())
        .spawn(move || loop {
            let Ok(sig) = set.wait() else { continue };
            if stop.is_set() {
                eprintln!(
                    "\ncadence: {sig} again: exiting at once (the simulated MCUs stop with this process)"
                );
                std::process::exit(i32::from(exit_code(sig)));
            }
            stop.set(sig);
            on_first(sig);
        })
        .map_err(|e| format!("cannot start the signal thread: {e}"))?;
    Ok(())
}
