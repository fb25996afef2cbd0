//! `cadence-mcu`: the simulated Klipper-protocol MCU on a pseudo-terminal (see `firmware::sim`).

fn main() {
    std::process::exit(firmware::sim::main_with_args(std::env::args()));
}
