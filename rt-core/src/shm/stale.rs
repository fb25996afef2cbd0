//! Half-created shared-memory storages of crashed processes.
//!
//! iceoryx2 creates a storage's shared memory with `shm_open` and sizes it a moment later. A
//! process killed between the two leaves a zero-size `iox2_*` object in `/dev/shm`, and
//! iceoryx2 0.10's opener waits for such an object to get a size without any time limit: every
//! later node creation that cleans up the dead process's resources (as [`super::open_node`]
//! does) then hangs for ever. A storage that is still zero bytes long after [`UNSIZED_MAX_AGE`]
//! belongs to a dead creator (a live one sizes it within microseconds), so it is removed, and
//! [`ensure_sweeper`] keeps removing such storages for the life of the process, which also
//! frees a call already waiting on one (it sees the object gone and fails cleanly).

use std::path::Path;
use std::time::{Duration, SystemTime};

/// Where POSIX shared memory objects live on Linux.
pub const SHM_DIR: &str = "/dev/shm";

/// The file name prefix of iceoryx2's objects (its default configuration).
pub const ICEORYX2_PREFIX: &str = "iox2_";

/// How long a zero-size storage may stay zero-size before it counts as a dead creator's.
pub const UNSIZED_MAX_AGE: Duration = Duration::from_secs(10);

/// Removes the zero-size files in `dir` whose names start with `prefix` and which were last
/// modified at least `min_age` ago. Files this process may not remove (another user's) and
/// files that vanish meanwhile are skipped. Returns how many were removed.
pub fn remove_unsized_storages(dir: &Path, prefix: &str, min_age: Duration) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let now = SystemTime::now();
    let mut removed = 0;
    for entry in entries.flatten() {
        if !entry.file_name().to_string_lossy().starts_with(prefix) {
            continue;
        }
        let Ok(meta) = entry.metadata() else {
            continue;
        };
        if !meta.is_file() || meta.len() != 0 {
            continue;
        }
        let old_enough = meta
            .modified()
            .ok()
            .and_then(|m| now.duration_since(m).ok())
            .is_some_and(|age| age >= min_age);
        if old_enough && std::fs::remove_file(entry.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// How often the sweeper looks again.
const SWEEP_EVERY: Duration = Duration::from_secs(1);

/// Sweeps once now, then starts (once per process) a sleeping background thread that sweeps
/// every [`SWEEP_EVERY`] for the life of the process. Any iceoryx2 call that cleans up a dead
/// process's resources (node creation and drop, service open, port creation) can meet a
/// half-created storage; the sweeper removes it once it is [`UNSIZED_MAX_AGE`] old, and the
/// waiting call then sees it gone and returns. Without a thread to spare, only the sweep now.
pub fn ensure_sweeper() {
    static STARTED: std::sync::Once = std::sync::Once::new();
    remove_unsized_storages(Path::new(SHM_DIR), ICEORYX2_PREFIX, UNSIZED_MAX_AGE);
    STARTED.call_once(|| {
        let _ = std::thread::Builder::new()
            .name("iox2-sweep".into())
            .spawn(|| loop {
                std::thread::sleep(SWEEP_EVERY);
                remove_unsized_storages(Path::new(SHM_DIR), ICEORYX2_PREFIX, UNSIZED_MAX_AGE);
            });
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(tag: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("cadence-stale-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn age(path: &Path, by: Duration) {
        let f = std::fs::File::options().write(true).open(path).unwrap();
        f.set_modified(SystemTime::now() - by).unwrap();
    }

    #[test]
    fn only_old_zero_size_objects_with_the_prefix_go() {
        let d = dir("sweep");
        let old_empty = d.join("iox2_a.dynamic");
        let new_empty = d.join("iox2_b.dynamic");
        let old_sized = d.join("iox2_c.dynamic");
        let other = d.join("other_d");
        std::fs::write(&old_empty, b"").unwrap();
        std::fs::write(&new_empty, b"").unwrap();
        std::fs::write(&old_sized, b"x").unwrap();
        std::fs::write(&other, b"").unwrap();
        for p in [&old_empty, &old_sized, &other] {
            age(p, Duration::from_secs(60));
        }
        assert_eq!(remove_unsized_storages(&d, ICEORYX2_PREFIX, UNSIZED_MAX_AGE), 1);
        assert!(!old_empty.exists());
        assert!(new_empty.exists() && old_sized.exists() && other.exists());
        // Once old enough, the other zero-size object goes too.
        age(&new_empty, Duration::from_secs(60));
        assert_eq!(remove_unsized_storages(&d, ICEORYX2_PREFIX, UNSIZED_MAX_AGE), 1);
        assert!(!new_empty.exists());
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_missing_directory_removes_nothing() {
        let d = std::env::temp_dir().join(format!("cadence-stale-none-{}", std::process::id()));
        assert_eq!(remove_unsized_storages(&d, ICEORYX2_PREFIX, Duration::ZERO), 0);
    }
}
