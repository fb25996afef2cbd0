//! Parser tests: syntax, errors, streaming, and properties (no panic, round trip).
use super::*;
use proptest::prelude::*;

fn parse(s: &str) -> Result<Option<Command>, GcodeError> {
    parse_line(7, s.as_bytes())
}

fn mv(x: Option<f64>, y: Option<f64>, z: Option<f64>, e: Option<f64>, f: Option<f64>) -> Command {
    Command::Move { x, y, z, e, f }
}

#[test]
fn moves_and_numbers() {
    assert_eq!(
        parse("G1 X10.5 Y-3 E.4 F1200").unwrap(),
        Some(mv(Some(10.5), Some(-3.0), None, Some(0.4), Some(1200.0)))
    );
    assert_eq!(
        parse("g0x1y+2z-.5").unwrap(),
        Some(mv(Some(1.0), Some(2.0), Some(-0.5), None, None))
    );
    assert_eq!(
        parse("G01 X3.").unwrap(),
        Some(mv(Some(3.0), None, None, None, None))
    );
    assert_eq!(
        parse("G1 F1800.000").unwrap(),
        Some(mv(None, None, None, None, Some(1800.0)))
    );
    assert_eq!(
        parse("  G1 X1 ; move (not a comment here)").unwrap(),
        Some(mv(Some(1.0), None, None, None, None))
    );
    assert_eq!(
        parse("G1 (go) X1 (there)").unwrap(),
        Some(mv(Some(1.0), None, None, None, None))
    );
}

#[test]
fn skips_blank_and_comment_lines() {
    for s in ["", "   ", "; hello", "(just a comment)", "N10", "%", "\r"] {
        assert_eq!(parse(s).unwrap(), None, "{s:?}");
    }
}

#[test]
fn other_commands() {
    let c = parse("M104 S200 ; heat").unwrap();
    assert_eq!(
        c,
        Some(Command::Other {
            name: "M104".into(),
            raw: "M104 S200".into()
        })
    );
    let c = parse("set_velocity_limit ACCEL=1000 SQUARE_CORNER_VELOCITY=5").unwrap();
    assert!(matches!(c, Some(Command::Other { ref name, .. }) if name == "SET_VELOCITY_LIMIT"));
    let c = parse("M117 Printing benchy... 12%").unwrap();
    assert!(
        matches!(c, Some(Command::Other { ref name, ref raw }) if name == "M117" && raw.ends_with("12%"))
    );
    assert!(matches!(parse("T0").unwrap(), Some(Command::Other { ref name, .. }) if name == "T0"));
    assert!(matches!(parse("G29.1").unwrap(), Some(Command::Other { ref name, .. }) if name == "G29.1"));
}

#[test]
fn modal_and_misc_commands() {
    assert_eq!(
        parse("G28").unwrap(),
        Some(Command::Home {
            x: true,
            y: true,
            z: true
        })
    );
    assert_eq!(
        parse("G28 X0").unwrap(),
        Some(Command::Home {
            x: true,
            y: false,
            z: false
        })
    );
    assert_eq!(
        parse("G28 Y Z").unwrap(),
        Some(Command::Home {
            x: false,
            y: true,
            z: true
        })
    );
    assert_eq!(parse("G90").unwrap(), Some(Command::AbsolutePositioning));
    assert_eq!(parse("G91").unwrap(), Some(Command::RelativePositioning));
    assert_eq!(parse("M82").unwrap(), Some(Command::AbsoluteExtrusion));
    assert_eq!(parse("M83").unwrap(), Some(Command::RelativeExtrusion));
    assert_eq!(parse("M400").unwrap(), Some(Command::WaitMoves));
    assert_eq!(
        parse("G92 E0").unwrap(),
        Some(Command::SetPosition {
            x: None,
            y: None,
            z: None,
            e: Some(0.0)
        })
    );
    assert_eq!(parse("G4 P500").unwrap(), Some(Command::Dwell { seconds: 0.5 }));
    assert_eq!(parse("G4 S2").unwrap(), Some(Command::Dwell { seconds: 2.0 }));
    assert_eq!(parse("G4").unwrap(), Some(Command::Dwell { seconds: 0.0 }));
}

#[test]
fn line_numbers_and_checksums() {
    let body = "N123 G1 X10";
    let cs = body.bytes().fold(0u8, |a, b| a ^ b);
    let line = format!("{body}*{cs}");
    assert_eq!(
        parse(&line).unwrap(),
        Some(mv(Some(10.0), None, None, None, None))
    );
    let bad = format!("{body}*{}", cs.wrapping_add(1));
    let e = parse(&bad).unwrap_err();
    assert!(matches!(e.kind, GcodeErrorKind::ChecksumMismatch { .. }), "{e}");
    assert!(matches!(
        parse("G1 X1*").unwrap_err().kind,
        GcodeErrorKind::BadChecksum(_)
    ));
    assert!(matches!(
        parse("G1 X1*300").unwrap_err().kind,
        GcodeErrorKind::BadChecksum(_)
    ));
}

#[test]
fn errors_say_line_and_word() {
    let e = parse_line(12, b"G1 X1..2").unwrap_err();
    assert_eq!(e.to_string(), "line 12: bad number 'X1..2' in `G1 X1..2`");
    assert!(matches!(
        parse("G1 X1 X2").unwrap_err().kind,
        GcodeErrorKind::DuplicateParameter('X')
    ));
    assert!(matches!(
        parse("G1 X").unwrap_err().kind,
        GcodeErrorKind::MissingValue(_)
    ));
    assert!(matches!(
        parse("G1 X-").unwrap_err().kind,
        GcodeErrorKind::BadNumber(_)
    ));
    assert!(matches!(
        parse("G1 X1-2").unwrap_err().kind,
        GcodeErrorKind::BadNumber(_)
    ));
    let big = format!("G1 X1{}", "0".repeat(400));
    assert!(matches!(
        parse(&big).unwrap_err().kind,
        GcodeErrorKind::NotFinite(_)
    ));
    assert!(parse("G1 Xnan").is_err());
    assert!(matches!(
        parse("G1 Xinf").unwrap_err().kind,
        GcodeErrorKind::MissingValue(_)
    ));
    assert!(matches!(
        parse("G1 #5").unwrap_err().kind,
        GcodeErrorKind::BadWord(_)
    ));
    assert!(matches!(
        parse("#5").unwrap_err().kind,
        GcodeErrorKind::BadCommand(_)
    ));
    assert!(matches!(
        parse("G1 (oops").unwrap_err().kind,
        GcodeErrorKind::UnterminatedComment
    ));
    assert!(matches!(
        parse("G4 P-5").unwrap_err().kind,
        GcodeErrorKind::Negative(_)
    ));
    assert!(matches!(
        parse_line(1, b"G1 X\xff").unwrap_err().kind,
        GcodeErrorKind::NotUtf8
    ));
    assert!(matches!(
        parse_line(1, b"G1\x00X1").unwrap_err().kind,
        GcodeErrorKind::Binary(0)
    ));
    assert!(matches!(
        parse("BAD-NAME X=1").unwrap_err().kind,
        GcodeErrorKind::BadCommand(_)
    ));
}

#[test]
fn reader_streams_lines_with_numbers() {
    let text = "; header\nG90\n\nG1 X1 Y2\nG1 X1..2\r\nM83\n";
    let items: Vec<_> = GcodeReader::new(text.as_bytes()).collect();
    assert_eq!(items.len(), 4);
    assert_eq!(items[0].as_ref().unwrap().line_no, 2);
    assert_eq!(items[1].as_ref().unwrap().line_no, 4);
    assert_eq!(items[2].as_ref().unwrap_err().line, 5);
    assert_eq!(
        items[3].as_ref().unwrap(),
        &GcodeLine {
            line_no: 6,
            cmd: Command::RelativeExtrusion
        }
    );
}

#[test]
fn reader_caps_line_length() {
    let mut text = vec![b'M'; MAX_LINE_LEN + 10];
    text.extend_from_slice(b"\nG90");
    let items: Vec<_> = GcodeReader::new(&text[..]).collect();
    assert_eq!(items.len(), 2);
    assert!(matches!(
        items[0].as_ref().unwrap_err().kind,
        GcodeErrorKind::LineTooLong
    ));
    assert_eq!(items[1].as_ref().unwrap().cmd, Command::AbsolutePositioning);
}

fn coord() -> impl Strategy<Value = Option<f64>> {
    prop_oneof![
        Just(None),
        (-1e6f64..1e6).prop_map(Some),
        (-1000i32..1000).prop_map(|v| Some(v as f64 / 8.0))
    ]
}

proptest! {
    #[test]
    fn never_panics_on_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        for item in GcodeReader::new(&bytes[..]) {
            let _ = item.map(|l| l.cmd.to_string()).map_err(|e| e.to_string());
        }
    }

    #[test]
    fn never_panics_on_gcode_like_text(s in "[GMNXYZEFPS*;()0-9 .+\\-=_a-z\n\t]{0,120}") {
        for item in GcodeReader::new(s.as_bytes()) {
            let _ = item.map(|l| l.cmd.to_string()).map_err(|e| e.to_string());
        }
    }

    #[test]
    fn moves_round_trip(x in coord(), y in coord(), z in coord(), e in coord(),
                        f in prop_oneof![Just(None), (1.0f64..1e5).prop_map(Some)]) {
        let cmd = Command::Move { x, y, z, e, f };
        let text = cmd.to_string();
        let back = parse_line(1, text.as_bytes()).unwrap();
        prop_assert_eq!(back, Some(cmd));
    }

    #[test]
    fn checksummed_lines_round_trip(n in 0u32..100000, x in -1000.0f64..1000.0) {
        let body = format!("N{n} G1 X{x}");
        let cs = body.bytes().fold(0u8, |a, b| a ^ b);
        let line = format!("{body}*{cs}");
        prop_assert_eq!(parse_line(1, line.as_bytes()).unwrap(), Some(mv(Some(x), None, None, None, None)));
    }
}

proptest! {
    #[test]
    fn other_params_never_panic(s in "[A-Z_0-9]{1,8}( [A-Za-z_=0-9.+\\-é]{0,12}){0,4}") {
        if let Ok(p) = OtherParams::parse(&s) {
            for k in p.keys().map(|k| k.to_string()).collect::<Vec<_>>() {
                let _ = p.float(&k);
            }
        }
    }
}

#[test]
fn other_params_both_styles() {
    let p = OtherParams::parse("M104 S215 T0").unwrap();
    assert_eq!(p.float("S"), Ok(Some(215.0)));
    assert_eq!(p.float("T"), Ok(Some(0.0)));
    let p = OtherParams::parse("SET_VELOCITY_LIMIT velocity=300 ACCEL=nan").unwrap();
    assert_eq!(p.float("VELOCITY"), Ok(Some(300.0)));
    assert!(p.float("ACCEL").is_err());
    assert!(OtherParams::parse("SET_VELOCITY_LIMIT VELOCITY").is_err());
    assert!(OtherParams::parse("M104 S2..5").is_err());
    // Quoted values hold spaces, as Klipper's shell-style parsing has them.
    let p = OtherParams::parse("RESPOND TYPE=command MSG=\"homed, printing\" PREFIX=x").unwrap();
    assert_eq!(p.get("MSG"), Some("homed, printing"));
    assert_eq!(p.get("PREFIX"), Some("x"));
    let keys: Vec<String> = p.keys().map(|k| k.as_str().to_string()).collect();
    assert_eq!(keys, ["TYPE", "MSG", "PREFIX"]);
    assert!(OtherParams::parse("RESPOND MSG=\"a b\" stray").is_err());
}

#[test]
fn long_command_names_and_texts_are_kept_whole() {
    let long = format!("my_macro_{}", "x".repeat(60));
    let line = format!("{long} A=1 B=2");
    let Some(Command::Other { name, raw }) = parse(&line).unwrap() else {
        panic!("not Other");
    };
    assert_eq!(name, long.to_ascii_uppercase());
    assert!(name.is_heap());
    assert_eq!(raw, line);
    // A text longer than the inline capacity.
    let text = format!("M117 {}", "é".repeat(150));
    let Some(Command::Other { name, raw }) = parse(&text).unwrap() else {
        panic!("not Other");
    };
    assert_eq!(name, "M117");
    assert!(!name.is_heap() && raw.is_heap());
    assert_eq!(raw, text);
    let frac = format!("G29.{}", "1".repeat(80));
    assert!(matches!(parse(&frac).unwrap(), Some(Command::Other { ref name, .. }) if *name == frac));
}

#[test]
fn usual_commands_are_stored_inline() {
    for s in [
        "M106 S255",
        "SET_VELOCITY_LIMIT VELOCITY=300 ACCEL=3000 ACCEL_TO_DECEL=1500 SQUARE_CORNER_VELOCITY=5",
        "EXCLUDE_OBJECT_START NAME=3DBenchy.stl_id_0_copy_0",
        "SET_PRESSURE_ADVANCE EXTRUDER=extruder ADVANCE=0.045 SMOOTH_TIME=0.04",
    ] {
        let Some(Command::Other { name, raw }) = parse(s).unwrap() else {
            panic!("{s}: not Other");
        };
        assert!(!name.is_heap() && !raw.is_heap(), "{s}");
        assert_eq!(raw, s);
    }
}

#[test]
fn many_parameters() {
    let mut line = String::from("MY_MACRO");
    for i in 0..100 {
        line.push_str(&format!(" key_{i}={i}.5"));
    }
    let p = OtherParams::parse(&line).unwrap();
    for i in 0..100 {
        assert_eq!(p.float(&format!("KEY_{i}")), Ok(Some(i as f64 + 0.5)));
    }
    assert_eq!(p.keys().count(), 100);
    assert_eq!(p.keys().nth(7).unwrap(), "KEY_7");
    let letters: String = ('A'..='Z')
        .filter(|c| !"GMN".contains(*c))
        .map(|c| format!(" {c}1"))
        .collect();
    let line = format!("M999{letters}");
    let p = OtherParams::parse(&line).unwrap();
    assert_eq!(p.keys().count(), 23);
    assert_eq!(p.get("Z"), Some("1"));
    assert_eq!(p.get("z"), None);
    assert_eq!(p.get("ZZ"), None);
}

#[test]
fn other_params_lookup_rules() {
    let p = OtherParams::parse("SET_X a=1 A=2 long_key=x").unwrap();
    assert_eq!(p.get("A"), Some("1"), "the first of a repeated key counts");
    assert_eq!(p.get("a"), None, "lookups are by the upper-case key");
    assert_eq!(p.get("LONG_KEY"), Some("x"));
    assert_eq!(
        p.float("LONG_KEY"),
        Err(GcodeErrorKind::BadNumber("LONG_KEY=x".into()))
    );
    let keys: Vec<String> = p.keys().map(|k| k.to_string()).collect();
    assert_eq!(keys, ["A", "A", "LONG_KEY"]);
    let p = OtherParams::parse("M104 S T0").unwrap();
    assert_eq!(p.get("S"), Some(""));
    assert_eq!(p.get("T"), Some("0"));
    assert_eq!(p.get("X"), None);
}

/// The parameters as the first (allocating) implementation kept them: (upper-cased key, value).
fn reference_pairs(raw: &str) -> Option<Vec<(String, String)>> {
    let raw = raw.trim();
    let name = first_word_ref(raw);
    let rest = &raw[name.len()..];
    let extended = !name.as_bytes().get(1).is_some_and(|b| b.is_ascii_digit());
    if !extended {
        return None;
    }
    let mut pairs = Vec::new();
    for tok in rest.split_ascii_whitespace() {
        let (k, v) = tok.split_once('=')?;
        if k.is_empty() || !k.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
            return None;
        }
        pairs.push((k.to_ascii_uppercase(), v.to_string()));
    }
    Some(pairs)
}

fn first_word_ref(s: &str) -> &str {
    s.split(|c: char| c.is_ascii_whitespace()).next().unwrap_or(s)
}

proptest! {
    #[test]
    fn other_params_match_the_reference(
        name in "[A-Za-z_]{2,8}",
        toks in proptest::collection::vec("[A-Za-z_0-9]{0,4}(=[A-Za-z0-9.=\\-]{0,5})?", 0..8),
        probe in "[A-Za-z_0-9]{1,4}",
    ) {
        let raw = format!("{name} {}", toks.join(" "));
        let got = OtherParams::parse(&raw);
        match reference_pairs(&raw) {
            None => prop_assert!(got.is_err()),
            Some(pairs) => {
                let p = got.unwrap();
                let keys: Vec<String> = p.keys().map(|k| k.to_string()).collect();
                let want: Vec<String> = pairs.iter().map(|(k, _)| k.clone()).collect();
                prop_assert_eq!(keys, want);
                for key in pairs.iter().map(|(k, _)| k.as_str()).chain([probe.as_str()]) {
                    let want = pairs.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str());
                    prop_assert_eq!(p.get(key), want);
                }
            }
        }
    }
}

proptest! {
    /// The fast decimal path gives exactly what `str::parse` gives.
    #[test]
    fn numbers_parse_like_str_parse(
        sign in "[+-]?",
        int in "[0-9]{0,18}",
        frac in proptest::option::of("[0-9]{0,25}"),
    ) {
        let text = match &frac {
            Some(f) => format!("{sign}{int}.{f}"),
            None => format!("{sign}{int}"),
        };
        let word = format!("X{text}");
        let digits = int.len() + frac.as_ref().map_or(0, |f| f.len());
        match super::number(&word) {
            Ok(v) => {
                let want: f64 = text.parse().unwrap();
                prop_assert_eq!(v.to_bits(), want.to_bits(), "{}", word);
            }
            Err(_) => prop_assert_eq!(digits, 0, "{} refused", word),
        }
    }
}

#[test]
fn number_edge_cases_parse_like_str_parse() {
    for text in [
        "0",
        "-0",
        "+0",
        ".5",
        "5.",
        "-.000",
        "95.551",
        "-0.01776",
        "999999999999999",
        "9999999999999999",
        "0.1234567890123456789012",
        "123456.78901234567",
        "1e5",
    ] {
        let word = format!("X{text}");
        match (super::number(&word), text.parse::<f64>()) {
            (Ok(v), Ok(want)) => assert_eq!(v.to_bits(), want.to_bits(), "{word}"),
            (Err(_), _) if text.contains('e') => {}
            (got, want) => panic!("{word}: {got:?} vs {want:?}"),
        }
    }
}
