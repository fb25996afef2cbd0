//! The telemetry thread: summaries of the latency histograms on `cadence/<instance>/telemetry`
//! about once a second, for outside monitors (never stalls the printer: overflow allowed).

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use rt_core::shm::{open_node, telemetry_service_name, ChannelConfig, ShmPublisher, Telemetry};

use crate::latency::Hists;
use crate::planner_thread::Ipc;

/// The telemetry thread: publishes the histogram summaries of `sources` on
/// `cadence/<instance>/telemetry` about once a second until `stop`, then once more. A thread of
/// its own (not real-time): summarising histograms is no work for the planner's loop.
pub(crate) fn telemetry_thread(
    instance: &str,
    hists: &Hists,
    started: Instant,
    sources: u32,
    stop: &AtomicBool,
) -> Result<(), rt_core::shm::ShmError> {
    let (node, _) = open_node::<Ipc>(&format!("cadence-telemetry-{}", std::process::id()))?;
    let mut publisher = ShmPublisher::<Ipc, Telemetry>::open(
        &node,
        &telemetry_service_name(instance),
        &ChannelConfig::telemetry(),
    )?;
    let mut last = Instant::now();
    // Acquire pairs with the Release store of whoever stops the print.
    while !stop.load(Ordering::Acquire) {
        std::thread::sleep(Duration::from_millis(50));
        if last.elapsed() >= Duration::from_secs(1) {
            last = Instant::now();
            hists.publish(&mut publisher, started.elapsed().as_nanos() as u64, sources);
        }
    }
    hists.publish(&mut publisher, started.elapsed().as_nanos() as u64, sources);
    Ok(())
}
