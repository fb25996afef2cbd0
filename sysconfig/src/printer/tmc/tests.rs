//! Whole-config tests of the TMC sections: registers as Klipper computes them, the virtual
//! endstop's rules and the errors naming file:line [section] option.

use crate::printer::{parse_str, PrinterConfig, TmcBus, TmcModel};
use std::path::Path;

const BASE: &str = "[mcu]\nserial: /dev/ttyACM0\n\
    [printer]\nkinematics: cartesian\nmax_velocity: 300\nmax_accel: 3000\n\
    [stepper_x]\nstep_pin: PA0\ndir_pin: PA1\nmicrosteps: 16\nrotation_distance: 40\nposition_max: 200\n\
    endstop_pin: tmc2209_stepper_x:virtual_endstop\nposition_endstop: 0\nhoming_retract_dist: 0\n\
    [stepper_y]\nstep_pin: PB0\ndir_pin: PB1\nmicrosteps: 16\nrotation_distance: 40\nposition_max: 200\n\
    endstop_pin: PB2\nposition_endstop: 0\n\
    [stepper_z]\nstep_pin: PC0\ndir_pin: PC1\nmicrosteps: 16\nrotation_distance: 8\nposition_max: 200\n\
    endstop_pin: PC2\nposition_endstop: 0\n";

fn parse(text: &str) -> Result<PrinterConfig, String> {
    parse_str(text, Path::new("printer.cfg")).map_err(|e| e.to_string())
}

#[test]
fn tmc2209_registers_follow_klipper() {
    let cfg = parse(&format!(
        "{BASE}[tmc2209 stepper_x]\nuart_pin: PD1\nuart_address: 3\nrun_current: 0.8\nhold_current: 0.5\n\
         diag_pin: ^PD2\ndriver_SGTHRS: 100\nstealthchop_threshold: 999999\n"
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let t = &cfg.tmc[0];
    assert_eq!((t.model, t.stepper.as_str()), (TmcModel::Tmc2209, "stepper_x"));
    let TmcBus::Uart {
        uart_pin,
        tx_pin,
        address,
        ..
    } = &t.bus
    else {
        panic!("not uart")
    };
    assert_eq!(
        (uart_pin.pin.as_str(), tx_pin.is_none(), *address),
        ("PD1", true, 3)
    );
    assert_eq!(
        t.diag_pin.as_ref().map(|p| (p.pin.as_str(), p.pullup)),
        Some(("PD2", true))
    );
    let f = &t.fields;
    let order: Vec<&str> = f.registers().iter().map(|r| r.0).collect();
    assert_eq!(
        order,
        [
            "GCONF",
            "SLAVECONF",
            "CHOPCONF",
            "IHOLD_IRUN",
            "TPWMTHRS",
            "TCOOLTHRS",
            "COOLCONF",
            "PWMCONF",
            "TPOWERDOWN",
            "SGTHRS"
        ]
    );
    // pdn_disable, mstep_reg_select, multistep_filt; stealthChop on (en_spreadcycle 0).
    assert_eq!(f.register("GCONF"), (1 << 6) | (1 << 7) | (1 << 8));
    assert_eq!(f.register("SLAVECONF"), 2 << 8);
    // toff 3, hstrt 5, tbl 2, vsense, mres 4 (16 microsteps), intpol.
    assert_eq!(
        f.register("CHOPCONF"),
        3 | (5 << 4) | (2 << 15) | (1 << 17) | (4 << 24) | (1 << 28)
    );
    assert_eq!(f.register("IHOLD_IRUN"), 15 | (25 << 8) | (8 << 16));
    // 12 MHz · (40 / 3200 / 16 mm) / 999999 mm/s + ½ → 0.
    assert_eq!(f.register("TPWMTHRS"), 0);
    assert_eq!(f.register("SGTHRS"), 100);
    assert_eq!(
        f.register("PWMCONF"),
        36 | (14 << 8) | (1 << 16) | (1 << 18) | (1 << 19) | (8 << 24) | (12 << 28)
    );
    assert_eq!(f.register("TPOWERDOWN"), 20);
}

#[test]
fn tmc2130_and_5160_over_spi() {
    let base = BASE.replace("tmc2209_stepper_x", "tmc5160_stepper_x");
    let cfg = parse(&format!(
        "{base}[tmc5160 stepper_x]\ncs_pin: PD1\nspi_software_sclk_pin: PD3\nspi_software_mosi_pin: PD4\n\
         spi_software_miso_pin: PD5\nrun_current: 2.0\nhold_current: 1.0\ndiag1_pin: ^!PD2\ndriver_SGT: -3\n\
         [tmc2130 stepper_y]\ncs_pin: PD6\nspi_software_sclk_pin: PD3\nspi_software_mosi_pin: PD4\n\
         spi_software_miso_pin: PD5\nrun_current: 0.6\ninterpolate: False\nstealthchop_threshold: 10\n"
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let x = cfg.tmc.iter().find(|t| t.model == TmcModel::Tmc5160).unwrap();
    assert_eq!(x.fields.get("globalscaler"), Some(167));
    assert_eq!(
        (x.fields.get("irun"), x.fields.get("ihold")),
        (Some(31), Some(15))
    );
    assert_eq!(x.fields.get("sgt"), Some(-3));
    assert_eq!(x.diag_field, Some("diag1_stall"));
    assert!(x.virtual_endstop && x.diag_pin.as_ref().is_some_and(|p| p.invert && p.pullup));
    let y = cfg.tmc.iter().find(|t| t.model == TmcModel::Tmc2130).unwrap();
    assert_eq!(
        (y.fields.get("intpol"), y.fields.get("en_pwm_mode")),
        (Some(0), Some(1))
    );
    // 13.2 MHz · (40 / 3200 / 16) / 10 + ½ = 1031.75 → 1031.
    assert_eq!(y.fields.get("tpwmthrs"), Some(1031));
    assert_eq!(y.fields.get("toff"), Some(4));
    assert!(!y.virtual_endstop);
}

#[test]
fn errors_name_file_line_section_and_option() {
    let uart = "[tmc2209 stepper_x]\nuart_pin: PD1\ndiag_pin: PD2\n";
    let cases = [
        (format!("{uart}run_current: 2.5\n"), "printer.cfg:35: [tmc2209 stepper_x] run_current: must have maximum of 2, got 2.5"),
        (format!("{uart}run_current: 0.5\nuart_address: 4\n"), "uart_address"),
        (format!("{uart}run_current: 0.5\ndriver_SGTHRS: 256\n"), "driver_sgthrs"),
        (format!("{uart}run_current: 0.5\ndriver_TOFF: 16\n"), "driver_toff"),
        (format!("{uart}run_current: 0.5\ndriver_BOGUS: 1\n"), "driver_bogus"),
        ("[tmc2209 stepper_x]\nuart_pin: PD1\nrun_current: 0.5\n".to_string(), "requires diag pin"),
        (format!("{uart}run_current: 0.5\n[tmc2209 stepper_q]\nuart_pin: PD1\nuart_address: 1\nrun_current: 1\n"), "Could not find config section '[stepper_q]'"),
        (format!("{uart}run_current: 0.5\nselect_pins: PE1, ebb:PE2\n"), "TMC mux pins must be on the same mcu"),
    ];
    for (extra, want) in cases {
        let err = parse(&format!("{BASE}{extra}")).err().unwrap_or_default();
        assert!(err.contains(want), "{extra}: {err}");
        assert!(err.starts_with("printer.cfg:"), "{err}");
    }
    let inverted = BASE.replace(
        "tmc2209_stepper_x:virtual_endstop",
        "!tmc2209_stepper_x:virtual_endstop",
    );
    let err = parse(&format!("{inverted}{uart}run_current: 0.5\n"))
        .err()
        .unwrap_or_default();
    assert!(err.contains("Can not pullup/invert tmc virtual pin"), "{err}");
}

#[test]
fn drivers_share_a_uart_line_and_an_unused_diag_pin_is_not_claimed() {
    let base = BASE.replace("tmc2209_stepper_x:virtual_endstop", "PD2");
    let cfg = parse(&format!(
        "{base}[tmc2209 stepper_x]\nuart_pin: PD1\nrun_current: 0.5\ndiag_pin: PD2\n\
         [tmc2209 stepper_y]\nuart_pin: PD1\nuart_address: 1\nrun_current: 0.5\n"
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(cfg.tmc.len(), 2);
    assert!(cfg.tmc.iter().all(|t| !t.virtual_endstop));
}

#[test]
fn tmc2240_current_follows_rref_and_uart_is_refused() {
    let base = BASE.replace("tmc2209_stepper_x", "tmc2240_stepper_x");
    let cfg = parse(&format!(
        "{base}[tmc2240 stepper_x]\ncs_pin: PD1\nrun_current: 0.8\nhold_current: 0.5\n\
         diag0_pin: ^!PD2\ndriver_SG4_THRS: 20\n"
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let t = &cfg.tmc[0];
    assert_eq!((t.model, t.sense_resistor), (TmcModel::Tmc2240, 12000.0));
    assert_eq!(t.diag_field, Some("diag0_stall"));
    let f = &t.fields;
    // 0.8 A needs range 1 (2.0 A peak with rref 12 kΩ): globalscaler 145, IRUN 31, IHOLD 19.
    for (field, v) in [
        ("current_range", 1),
        ("globalscaler", 145),
        ("irun", 31),
        ("ihold", 19),
        ("sg4_thrs", 20),
        ("sg4_angle_offset", 1),
        ("irundelay", 4),
        ("mres", 4),
    ] {
        assert_eq!(f.get(field), Some(v), "{field}");
    }
    let (run, hold) = crate::printer::tmc::current::current(f, t.sense_resistor);
    assert!(
        (run - 0.8).abs() < 0.03 && (hold - 0.5).abs() < 0.03,
        "{run} {hold}"
    );
    // The largest current with rref 12 kΩ is 36000 / 12000 / √2 = 2.12 A.
    let e = parse(&format!(
        "{base}[tmc2240 stepper_x]\ncs_pin: PD1\nrun_current: 2.2\ndiag0_pin: PD2\n"
    ))
    .unwrap_err();
    assert!(e.contains("[tmc2240 stepper_x] run_current"), "{e}");
    let e = parse(&format!(
        "{base}[tmc2240 stepper_x]\ncs_pin: PD1\nrun_current: 1\nrref: 1000\n"
    ))
    .unwrap_err();
    assert!(e.contains("rref"), "{e}");
    let e = parse(&format!(
        "{base}[tmc2240 stepper_x]\nuart_pin: PD1\nrun_current: 1\n"
    ))
    .unwrap_err();
    assert!(e.contains("'uart_pin' is not supported by Cadence yet"), "{e}");
}

#[test]
fn tmc2660_has_one_current_no_thresholds_and_klippers_checks() {
    let base = BASE.replace("tmc2209_stepper_x:virtual_endstop", "PA2");
    let cfg = parse(&format!(
        "{base}[tmc2660 stepper_x]\ncs_pin: PD1\nspi_bus: usart1\nrun_current: 1.0\nsense_resistor: 0.051\n\
         idle_current_percent: 20\n"
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let t = &cfg.tmc[0];
    assert_eq!((t.model, t.idle_current_percent), (TmcModel::Tmc2660, 20));
    let f = &t.fields;
    let order: Vec<&str> = f.registers().iter().map(|r| r.0).collect();
    assert_eq!(order, ["DRVCONF", "SGCSCONF", "DRVCTRL", "CHOPCONF", "SMARTEN"]);
    for (field, v) in [
        ("cs", 13),
        ("vsense", 1),
        ("mres", 4),
        ("intpol", 1),
        ("toff", 4),
        ("ts2g", 3),
    ] {
        assert_eq!(f.get(field), Some(v), "{field}");
    }
    let with = |extra: &str| {
        parse(&format!(
            "{base}[tmc2660 stepper_x]\ncs_pin: PD1\nrun_current: 1.0\nsense_resistor: 0.051\n{extra}"
        ))
    };
    for (extra, said) in [
        ("hold_current: 0.5\n", "hold_current"),
        ("stealthchop_threshold: 10\n", "stealthchop_threshold"),
        (
            "driver_HEND: 10\ndriver_HSTRT: 7\n",
            "driver_HEND + driver_HSTRT must be <= 15",
        ),
        ("idle_current_percent: 101\n", "idle_current_percent"),
    ] {
        let e = with(extra).unwrap_err();
        assert!(e.contains(said), "{extra}: {e}");
    }
    let e = parse(&format!(
        "{base}[tmc2660 stepper_x]\ncs_pin: PD1\nrun_current: 1.0\n"
    ))
    .unwrap_err();
    assert!(e.contains("sense_resistor"), "{e}");
}
