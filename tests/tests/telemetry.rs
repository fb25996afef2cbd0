//! An outside process can watch a live print: the host publishes histogram summaries on the
//! iceoryx2 service `cadence/p<pid>/telemetry` (layout: rt-core/src/shm.rs).

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cadence_tests::{bin, workspace};
use iceoryx2::prelude::ipc;
use rt_core::shm::{
    open_node, telemetry_kind, telemetry_service_name, ChannelConfig, ShmSubscriber, Telemetry,
};

#[test]
fn a_monitor_receives_lead_margin_summaries_during_a_print() {
    let gcode = workspace().join("examples/square.gcode");
    let mut child = Command::new(bin("cadence"))
        .args(["print", gcode.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start cadence");
    let service = telemetry_service_name(&format!("p{}", child.id()));
    let (node, _) = open_node::<ipc::Service>("telemetry-monitor").expect("node");
    let mut sub =
        ShmSubscriber::<ipc::Service, Telemetry>::open(&node, &service, &ChannelConfig::telemetry())
            .expect("subscribe")
            .accept_any_start();
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut lead_counts = Vec::new();
    while Instant::now() < deadline && child.try_wait().expect("wait").is_none() {
        let got = sub.recv_timeout_with(Duration::from_millis(100), |t| {
            (t.kind, t.source, t.count, t.values[0])
        });
        if let Ok(Some((kind, source, count, samples))) = got {
            if kind == telemetry_kind::HIST_SUMMARY && source == 0 && count >= 11 {
                lead_counts.push(samples);
            }
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    assert!(
        lead_counts.iter().any(|&n| n > 0.0),
        "no lead-margin summary with samples: {lead_counts:?}"
    );
}
