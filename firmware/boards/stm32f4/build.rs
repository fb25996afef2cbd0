//! Writes the data dictionary (zlib JSON from the core's one message table, this chip's pins
//! and `CLOCK_FREQ`) and the linker's memory map into `OUT_DIR`; links the image with
//! cortex-m-rt's script `link.x`.

use std::path::PathBuf;
use std::{env, fs};

#[path = "src/chip.rs"]
mod chip;

fn main() {
    let Some(out) = env::var_os("OUT_DIR").map(PathBuf::from) else {
        eprintln!("OUT_DIR is not set (run through cargo)");
        std::process::exit(1);
    };
    let dictionary = firmware::dict::dictionary_bytes_for(&chip::CHIP, chip::CLOCK_FREQ);
    if dictionary.is_empty() {
        eprintln!("the data dictionary did not compress");
        std::process::exit(1);
    }
    let writes = [
        ("dictionary.zlib", dictionary),
        ("memory.x", include_bytes!("memory.x").to_vec()),
    ];
    for (name, bytes) in writes {
        if let Err(e) = fs::write(out.join(name), bytes) {
            eprintln!("{}: {e}", out.join(name).display());
            std::process::exit(1);
        }
    }
    println!("cargo:rustc-link-search={}", out.display());
    // cortex-m-rt's linker script (it includes memory.x).
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=src/chip.rs");
}
