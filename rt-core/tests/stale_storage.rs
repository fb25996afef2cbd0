//! A process killed while iceoryx2 was creating a service leaves a zero-size, write-only
//! storage in /dev/shm; iceoryx2 0.10 waits on such a storage without a time limit. This test
//! makes one for real (a child process opens a service and is killed; the service's dynamic
//! storage is then put back in the state an interrupted creation leaves) and checks that the
//! next `open_node`, which cleans up the dead child, returns instead of hanging.
#![cfg(feature = "std")]

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::os::unix::fs::PermissionsExt;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, SystemTime};

use iceoryx2::prelude::ipc;
use rt_core::shm::stale::{ICEORYX2_PREFIX, SHM_DIR};
use rt_core::shm::{open_node, ChannelConfig, ShmPublisher, StepBatch};

const CHILD_ENV: &str = "CADENCE_STALE_STORAGE_CHILD";

fn dynamic_storages() -> BTreeSet<PathBuf> {
    std::fs::read_dir(SHM_DIR)
        .map(|it| {
            it.flatten()
                .map(|e| e.path())
                .filter(|p| {
                    let name = p
                        .file_name()
                        .map(|n| n.to_string_lossy().into_owned())
                        .unwrap_or_default();
                    name.starts_with(ICEORYX2_PREFIX) && name.ends_with(".dynamic")
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The child's part: opens a node and a service, names the dynamic storages that appeared,
/// then waits to be killed.
#[test]
fn child_opens_a_service_and_waits() {
    if std::env::var_os(CHILD_ENV).is_none() {
        return;
    }
    let before = dynamic_storages();
    let (node, _) = open_node::<ipc::Service>("stale-child").unwrap();
    let service = format!("cadence/stale-test-{}/steps", std::process::id());
    let _p = ShmPublisher::<ipc::Service, StepBatch>::open(&node, &service, &ChannelConfig::steps()).unwrap();
    for p in dynamic_storages().difference(&before) {
        println!("NEW {}", p.display());
    }
    println!("READY");
    std::thread::sleep(Duration::from_secs(600));
}

#[test]
fn a_dead_creators_zero_size_storage_does_not_hang_the_next_node() {
    if std::env::var_os(CHILD_ENV).is_some() {
        return;
    }
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "child_opens_a_service_and_waits",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env(CHILD_ENV, "1")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut new = Vec::new();
    for line in BufReader::new(child.stdout.take().unwrap()).lines() {
        let line = line.unwrap();
        if let Some(p) = line.strip_prefix("NEW ") {
            new.push(PathBuf::from(p));
        }
        if line.contains("READY") {
            break;
        }
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(
        !new.is_empty(),
        "the child's service made no dynamic storage in {SHM_DIR}"
    );
    // As an interrupted creation leaves it: zero bytes, write-only, and old.
    for p in &new {
        let f = std::fs::File::options().write(true).open(p).unwrap();
        f.set_len(0).unwrap();
        f.set_modified(SystemTime::now() - Duration::from_secs(60))
            .unwrap();
        std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o200)).unwrap();
    }
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(open_node::<ipc::Service>("stale-next").map(|_| ()));
    });
    rx.recv_timeout(Duration::from_secs(60))
        .expect("open_node hung on the dead child's zero-size storage")
        .unwrap();
    for p in &new {
        assert!(!p.exists(), "{} was left", p.display());
    }
}
