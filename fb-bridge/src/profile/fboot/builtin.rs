//! The built-in type table: port types of the FB types FORTE ships whose interface is
//! fixed, so a port wired to one of them is typed without the application's `.fbt` files.

use super::TypeTable;
use crate::types::ElementaryType;

/// Port types of the FB types whose interface is fixed by their name or by the standard
/// library FORTE ships, each read from FORTE's source:
///
/// - the IEC 61131-3 conversions `F_<A>_TO_<B>` (`IN`: A, `OUT`: B) for every pair of
///   elementary types (also `TOD`, `DT`), the BCD ones (`F_BYTE_BCD_TO_USINT`,
///   `F_USINT_TO_BCD_BYTE`, ...) and `F_TIME_IN_<unit>_TO_<B>` (`IN`: TIME);
/// - FORTE's data FBs `<T>2<T>` (`INT2INT`: `IN`, `OUT` INT);
/// - its event FBs with data: `E_CTU`/`E_CTD`/`E_CTUD` (`PV`, `CV` UINT, `Q`/`QU`/`QD`
///   BOOL), `E_CYCLE`, `E_DELAY`, `E_RDELAY` (`DT` TIME), `E_TRAIN` (`DT` TIME, `N`, `CV`
///   UINT), `E_DEMUX` (`K` UINT), `E_SWITCH`/`E_SELECT` (`G`), `E_PERMIT` (`PERMIT`),
///   `E_R_TRIG`/`E_F_TRIG` (`QI`), `E_D_FF` (`D`, `Q`), `E_SR`, `E_RS`, `E_T_FF` (`Q`),
///   all BOOL where not said;
/// - the IEC 61131-3 FBs: `FB_TON`/`FB_TOF`/`FB_TP`, `FB_CTU`/`FB_CTD`/`FB_CTUD` and
///   their `_DINT`, `_LINT`, `_UDINT`, `_ULINT` forms, `FB_R_TRIG`/`FB_F_TRIG`,
///   `FB_SR`/`FB_RS`;
/// - the process image: `IX`, `IB`, `IW`, `ID`, `IL` (`IN`: BOOL, BYTE, WORD, DWORD,
///   LWORD) and `QX` ... `QL` (`OUT`).
pub fn builtin_types() -> TypeTable {
    let mut table = TypeTable::new();
    let mut add = |fb_type: String, ports: &[(&str, &str)]| {
        let entry = table.entry(fb_type).or_default();
        for (port, ty) in ports {
            entry.insert((*port).to_owned(), (*ty).to_owned());
        }
    };
    let mut names: Vec<&str> = ElementaryType::ALL.iter().map(|t| t.name()).collect();
    names.extend(["TOD", "DT"]);
    for a in &names {
        for b in &names {
            if a != b {
                add(format!("F_{a}_TO_{b}"), &[("IN", a), ("OUT", b)]);
            }
        }
    }
    for (bits, unsigned) in [
        ("BYTE", "USINT"),
        ("WORD", "UINT"),
        ("DWORD", "UDINT"),
        ("LWORD", "ULINT"),
    ] {
        add(
            format!("F_{bits}_BCD_TO_{unsigned}"),
            &[("IN", bits), ("OUT", unsigned)],
        );
        add(
            format!("F_{unsigned}_TO_BCD_{bits}"),
            &[("IN", unsigned), ("OUT", bits)],
        );
    }
    for unit in ["S", "MS", "US", "NS"] {
        for out in ["LINT", "ULINT", "LREAL"] {
            add(
                format!("F_TIME_IN_{unit}_TO_{out}"),
                &[("IN", "TIME"), ("OUT", out)],
            );
        }
    }
    for t in ElementaryType::ALL {
        let t = t.name();
        add(format!("{t}2{t}"), &[("IN", t), ("OUT", t)]);
    }
    let fixed: &[(&str, &[(&str, &str)])] = &[
        ("E_CTU", &[("PV", "UINT"), ("Q", "BOOL"), ("CV", "UINT")]),
        ("E_CTD", &[("PV", "UINT"), ("Q", "BOOL"), ("CV", "UINT")]),
        (
            "E_CTUD",
            &[
                ("PV", "UINT"),
                ("QU", "BOOL"),
                ("QD", "BOOL"),
                ("CV", "UINT"),
            ],
        ),
        ("E_CYCLE", &[("DT", "TIME")]),
        ("E_DELAY", &[("DT", "TIME")]),
        ("E_RDELAY", &[("DT", "TIME")]),
        ("E_TRAIN", &[("DT", "TIME"), ("N", "UINT"), ("CV", "UINT")]),
        ("E_DEMUX", &[("K", "UINT")]),
        ("E_SWITCH", &[("G", "BOOL")]),
        ("E_SELECT", &[("G", "BOOL")]),
        ("E_PERMIT", &[("PERMIT", "BOOL")]),
        ("E_R_TRIG", &[("QI", "BOOL")]),
        ("E_F_TRIG", &[("QI", "BOOL")]),
        ("E_D_FF", &[("D", "BOOL"), ("Q", "BOOL")]),
        ("E_SR", &[("Q", "BOOL")]),
        ("E_RS", &[("Q", "BOOL")]),
        ("E_T_FF", &[("Q", "BOOL")]),
        ("FB_R_TRIG", &[("CLK", "BOOL"), ("Q", "BOOL")]),
        ("FB_F_TRIG", &[("CLK", "BOOL"), ("Q", "BOOL")]),
        ("FB_SR", &[("S1", "BOOL"), ("R", "BOOL"), ("Q1", "BOOL")]),
        ("FB_RS", &[("S", "BOOL"), ("R1", "BOOL"), ("Q1", "BOOL")]),
    ];
    for (fb_type, ports) in fixed {
        add((*fb_type).to_owned(), ports);
    }
    for timer in ["FB_TON", "FB_TOF", "FB_TP"] {
        add(
            timer.to_owned(),
            &[
                ("IN", "BOOL"),
                ("PT", "TIME"),
                ("Q", "BOOL"),
                ("ET", "TIME"),
            ],
        );
    }
    for (suffix, count) in [
        ("", "INT"),
        ("_DINT", "DINT"),
        ("_LINT", "LINT"),
        ("_UDINT", "UDINT"),
        ("_ULINT", "ULINT"),
    ] {
        add(
            format!("FB_CTU{suffix}"),
            &[
                ("CU", "BOOL"),
                ("R", "BOOL"),
                ("PV", count),
                ("Q", "BOOL"),
                ("CV", count),
            ],
        );
        add(
            format!("FB_CTD{suffix}"),
            &[
                ("CD", "BOOL"),
                ("LD", "BOOL"),
                ("PV", count),
                ("Q", "BOOL"),
                ("CV", count),
            ],
        );
        // FORTE has no FB_CTUD_UDINT.
        if suffix != "_UDINT" {
            add(
                format!("FB_CTUD{suffix}"),
                &[
                    ("CU", "BOOL"),
                    ("CD", "BOOL"),
                    ("R", "BOOL"),
                    ("LD", "BOOL"),
                    ("PV", count),
                    ("QU", "BOOL"),
                    ("QD", "BOOL"),
                    ("CV", count),
                ],
            );
        }
    }
    for (letter, ty) in [
        ("X", "BOOL"),
        ("B", "BYTE"),
        ("W", "WORD"),
        ("D", "DWORD"),
        ("L", "LWORD"),
    ] {
        add(format!("I{letter}"), &[("IN", ty)]);
        add(format!("Q{letter}"), &[("OUT", ty)]);
    }
    table
}
