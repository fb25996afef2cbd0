//! The TMC2660's registers and fields (its datasheet, rev. 1.08): an SPI driver of 20-bit
//! datagrams, register chosen by the datagram's top bits (no addresses, no read-back of
//! settings): DRVCTRL (`0`), CHOPCONF (`100`), SMARTEN (`101`), SGCSCONF (`110`), DRVCONF
//! (`111`). A register's "address" here is its selector as it sits in bits 19..16 of the
//! datagram (`0x8` for CHOPCONF…), so a datagram is `address << 16 | value`. Every datagram is
//! answered with a 20-bit status, whose content DRVCONF's `rdsel` chooses; the status is
//! kept as the 24 bits clocked in (the 20 status bits then 4 more), so its fields sit 4 bits up.

/// Registers: (name, selector in datagram bits 19..16). The `READRSP@RDSELn` are the status
/// answers (pseudo-addresses above the selectors, never sent).
pub const TMC2660_REGISTERS: &[(&str, u8)] = &[
    ("DRVCTRL", 0x0),
    ("CHOPCONF", 0x8),
    ("SMARTEN", 0xa),
    ("SGCSCONF", 0xc),
    ("DRVCONF", 0xe),
    ("READRSP@RDSEL0", 0x10),
    ("READRSP@RDSEL1", 0x11),
    ("READRSP@RDSEL2", 0x12),
];

/// The status answers (`DUMP_TMC`'s queried list).
pub const TMC2660_READABLE: &[&str] = &["READRSP@RDSEL0", "READRSP@RDSEL1", "READRSP@RDSEL2"];

/// Status bits every answer has.
const STATUS: [(&str, u32); 8] = [
    ("stallguard", 1 << 4),
    ("ot", 1 << 5),
    ("otpw", 1 << 6),
    ("s2ga", 1 << 7),
    ("s2gb", 1 << 8),
    ("ola", 1 << 9),
    ("olb", 1 << 10),
    ("stst", 1 << 11),
];

/// Fields: (register, field, mask).
pub const TMC2660_FIELDS: &[(&str, &str, u32)] = &[
    ("DRVCTRL", "mres", 0xf),
    ("DRVCTRL", "dedge", 1 << 8),
    ("DRVCTRL", "intpol", 1 << 9),
    ("CHOPCONF", "toff", 0xf),
    ("CHOPCONF", "hstrt", 0x7 << 4),
    ("CHOPCONF", "hend", 0xf << 7),
    ("CHOPCONF", "hdec", 0x3 << 11),
    ("CHOPCONF", "rndtf", 1 << 13),
    ("CHOPCONF", "chm", 1 << 14),
    ("CHOPCONF", "tbl", 0x3 << 15),
    ("SMARTEN", "semin", 0xf),
    ("SMARTEN", "seup", 0x3 << 5),
    ("SMARTEN", "semax", 0xf << 8),
    ("SMARTEN", "sedn", 0x3 << 13),
    ("SMARTEN", "seimin", 1 << 15),
    ("SGCSCONF", "cs", 0x1f),
    ("SGCSCONF", "sgt", 0x7f << 8),
    ("SGCSCONF", "sfilt", 1 << 16),
    ("DRVCONF", "rdsel", 0x3 << 4),
    ("DRVCONF", "vsense", 1 << 6),
    ("DRVCONF", "sdoff", 1 << 7),
    ("DRVCONF", "ts2g", 0x3 << 8),
    ("DRVCONF", "diss2g", 1 << 10),
    ("DRVCONF", "slpl", 0x3 << 12),
    ("DRVCONF", "slph", 0x3 << 14),
    ("DRVCONF", "tst", 1 << 16),
    ("READRSP@RDSEL0", "stallguard", STATUS[0].1),
    ("READRSP@RDSEL0", "ot", STATUS[1].1),
    ("READRSP@RDSEL0", "otpw", STATUS[2].1),
    ("READRSP@RDSEL0", "s2ga", STATUS[3].1),
    ("READRSP@RDSEL0", "s2gb", STATUS[4].1),
    ("READRSP@RDSEL0", "ola", STATUS[5].1),
    ("READRSP@RDSEL0", "olb", STATUS[6].1),
    ("READRSP@RDSEL0", "stst", STATUS[7].1),
    ("READRSP@RDSEL0", "mstep", 0x3ff << 14),
    ("READRSP@RDSEL1", "stallguard", STATUS[0].1),
    ("READRSP@RDSEL1", "ot", STATUS[1].1),
    ("READRSP@RDSEL1", "otpw", STATUS[2].1),
    ("READRSP@RDSEL1", "s2ga", STATUS[3].1),
    ("READRSP@RDSEL1", "s2gb", STATUS[4].1),
    ("READRSP@RDSEL1", "ola", STATUS[5].1),
    ("READRSP@RDSEL1", "olb", STATUS[6].1),
    ("READRSP@RDSEL1", "stst", STATUS[7].1),
    ("READRSP@RDSEL1", "sg_result", 0x3ff << 14),
    ("READRSP@RDSEL2", "stallguard", STATUS[0].1),
    ("READRSP@RDSEL2", "ot", STATUS[1].1),
    ("READRSP@RDSEL2", "otpw", STATUS[2].1),
    ("READRSP@RDSEL2", "s2ga", STATUS[3].1),
    ("READRSP@RDSEL2", "s2gb", STATUS[4].1),
    ("READRSP@RDSEL2", "ola", STATUS[5].1),
    ("READRSP@RDSEL2", "olb", STATUS[6].1),
    ("READRSP@RDSEL2", "stst", STATUS[7].1),
    ("READRSP@RDSEL2", "se", 0x1f << 14),
    ("READRSP@RDSEL2", "sg_result@rdsel2", 0x1f << 19),
];

/// Signed fields.
pub const TMC2660_SIGNED: &[&str] = &["sgt"];
