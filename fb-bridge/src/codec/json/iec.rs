//! IEC 61131-3 literals: durations, dates, times of day and based bit strings, read in
//! every spelling the standard allows and written in one canonical form.
//!
//! Pure string work, no JSON: `read` calls the parsers for JSON strings and `encode` the
//! formatters; [`excerpt`], which both this module's errors and `read`'s use, lives here
//! so that the two import one way only. Every slice is taken at an ASCII position or a
//! character boundary, so any UTF-8 input is safe.
use std::borrow::Cow;
use std::fmt::Write;

use crate::value::MS_PER_DAY;

/// Why a string is not a valid literal: its form, or a value beyond the type's range.
#[derive(Debug, PartialEq)]
pub enum LiteralError {
    Syntax(String),
    Range,
}

use LiteralError::{Range, Syntax};

fn syntax(why: impl Into<String>) -> LiteralError {
    Syntax(why.into())
}

/// At most 40 characters of `s`: error messages go back to devices and into logs, and a
/// 64 KiB string does not belong in either.
pub(super) fn excerpt(s: &str) -> String {
    const MAX: usize = 40;
    match s.char_indices().nth(MAX) {
        Some((cut, _)) => format!("{}...", &s[..cut]),
        None => s.to_owned(),
    }
}

/// `s` without the first of `prefixes` it starts with, compared case-insensitively.
fn strip_prefix<'a>(s: &'a str, prefixes: &[&str]) -> Option<&'a str> {
    prefixes.iter().find_map(|p| {
        s.get(..p.len())
            .filter(|head| head.eq_ignore_ascii_case(p))
            .map(|_| &s[p.len()..])
    })
}

/// Splits a run of digits in `radix` off the front of `s`, skipping single `_`
/// between digits (IEC 61131-3 allows `1_000_000`, `16#FF_FF`). `None` when `s`
/// does not start with a digit.
fn take_digits(s: &str, radix: u32) -> Option<(Cow<'_, str>, &str)> {
    let bytes = s.as_bytes();
    let is_digit = |b: Option<&u8>| b.is_some_and(|b| char::from(*b).is_digit(radix));
    if !is_digit(bytes.first()) {
        return None;
    }
    let mut end = 0;
    let mut separated = false;
    while end < bytes.len() {
        match bytes[end] {
            b if is_digit(Some(&b)) => {}
            b'_' if is_digit(bytes.get(end + 1)) => separated = true,
            _ => break,
        }
        end += 1;
    }
    // Only ASCII bytes were consumed, so `end` is a character boundary.
    let (run, rest) = s.split_at(end);
    // Only copied when there are `_` to drop.
    let digits = if separated {
        Cow::Owned(run.replace('_', ""))
    } else {
        Cow::Borrowed(run)
    };
    Some((digits, rest))
}

/// A based literal `16#FF`, `8#17` or `2#1010`.
pub fn parse_bit_string(s: &str) -> Result<i128, LiteralError> {
    let expected = "expected 16#.., 8#.. or 2#..";
    let (base, rest) = s.split_once('#').ok_or_else(|| syntax(expected))?;
    let radix = match base {
        "16" => 16,
        "8" => 8,
        "2" => 2,
        _ => return Err(syntax(expected)),
    };
    let (digits, rest) =
        take_digits(rest, radix).ok_or_else(|| syntax(format!("no base-{radix} digits")))?;
    if !rest.is_empty() {
        return Err(syntax(format!(
            "not a base-{radix} digit at {:?}",
            excerpt(rest)
        )));
    }
    // The digits are valid, so this fails only when the number overflows.
    let n = u128::from_str_radix(&digits, radix).map_err(|_| Range)?;
    i128::try_from(n).map_err(|_| Range)
}

/// Duration units, largest first, with their length in nanoseconds.
const TIME_UNITS: [(&str, u128); 7] = [
    ("d", 86_400_000_000_000),
    ("h", 3_600_000_000_000),
    ("m", 60_000_000_000),
    ("s", 1_000_000_000),
    ("ms", 1_000_000),
    ("us", 1_000),
    ("ns", 1),
];

/// A duration `T#1h2m3s4ms5us`, `TIME#-1.5s`, `t#1h_30m` in microseconds.
///
/// Sums in `u128` nanoseconds, so any literal that fits `TIME` is computed exactly
/// and anything larger is [`Range`] rather than an overflow.
pub fn parse_time(s: &str) -> Result<i64, LiteralError> {
    let body = strip_prefix(s, &["TIME#", "T#"]).ok_or_else(|| syntax("expected T#.."))?;
    let (negative, mut rest) = match body.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, body),
    };
    if rest.is_empty() {
        return Err(syntax("no duration"));
    }
    let mut total_ns: u128 = 0;
    let mut previous_unit = None;
    let mut had_fraction = false;
    while !rest.is_empty() {
        if had_fraction {
            return Err(syntax("only the last unit may have a fraction"));
        }
        let (whole, after) = take_digits(rest, 10)
            .ok_or_else(|| syntax(format!("expected a number at {:?}", excerpt(rest))))?;
        let (fraction, after) = match after.strip_prefix('.') {
            Some(f) => {
                let (digits, after) =
                    take_digits(f, 10).ok_or_else(|| syntax("expected digits after '.'"))?;
                (Some(digits), after)
            }
            None => (None, after),
        };
        let unit_end = after
            .find(|c: char| !c.is_ascii_alphabetic())
            .unwrap_or(after.len());
        let (unit, after) = after.split_at(unit_end);
        let index = unit_index(unit)?;
        if previous_unit.is_some_and(|p| index <= p) {
            return Err(syntax("units go from largest to smallest, each once"));
        }
        previous_unit = Some(index);
        let ns = component_ns(&whole, fraction.as_deref(), TIME_UNITS[index].1)?;
        total_ns = total_ns.checked_add(ns).ok_or(Range)?;
        had_fraction = fraction.is_some();
        rest = match after.strip_prefix('_') {
            Some(next) if next.starts_with(|c: char| c.is_ascii_digit()) => next,
            _ => after,
        };
    }
    // (Remainders rather than `is_multiple_of`, which needs Rust 1.87.)
    let (us, leftover_ns) = (total_ns / 1_000, total_ns % 1_000);
    if leftover_ns != 0 {
        return Err(syntax("not a whole number of microseconds"));
    }
    let us = i128::try_from(us).map_err(|_| Range)?;
    i64::try_from(if negative { -us } else { us }).map_err(|_| Range)
}

fn unit_index(unit: &str) -> Result<usize, LiteralError> {
    if unit.is_empty() {
        return Err(syntax("a number without a unit"));
    }
    TIME_UNITS
        .iter()
        .position(|(name, _)| name.eq_ignore_ascii_case(unit))
        .ok_or_else(|| {
            syntax(format!(
                "unknown unit {:?}: expected d, h, m, s, ms, us or ns",
                excerpt(unit)
            ))
        })
}

/// `whole.fraction` units of `unit_ns` nanoseconds each, exactly.
fn component_ns(whole: &str, fraction: Option<&str>, unit_ns: u128) -> Result<u128, LiteralError> {
    // Only digits, so parsing fails only on overflow.
    let whole: u128 = whole.parse().map_err(|_| Range)?;
    let mut ns = whole.checked_mul(unit_ns).ok_or(Range)?;
    let fraction = fraction.unwrap_or("").trim_end_matches('0');
    if !fraction.is_empty() {
        // A day is 864 * 10^11 ns, so more than 16 significant fraction digits can
        // never be whole nanoseconds; the cap also keeps the product below 10^32.
        let finer = || syntax("finer than a nanosecond");
        if fraction.len() > 18 {
            return Err(finer());
        }
        let scale = 10u128.pow(fraction.len() as u32);
        let scaled = fraction.parse::<u128>().map_err(|_| Range)? * unit_ns;
        let (fraction_ns, leftover) = (scaled / scale, scaled % scale);
        if leftover != 0 {
            return Err(finer());
        }
        ns = ns.checked_add(fraction_ns).ok_or(Range)?;
    }
    Ok(ns)
}

/// `T#` and the non-zero units from days down: `T#1h2m3s4ms5us`, `T#-1s`, `T#0s`.
pub fn format_time(us: i64) -> String {
    if us == 0 {
        return "T#0s".to_owned();
    }
    let mut out = String::from(if us < 0 { "T#-" } else { "T#" });
    let mut rest = u128::from(us.unsigned_abs()) * 1_000;
    for (name, unit_ns) in &TIME_UNITS[..6] {
        let n = rest / unit_ns;
        rest %= unit_ns;
        if n > 0 {
            let _ = write!(out, "{n}{name}");
        }
    }
    out
}

/// A date `D#2026-11-22` or `DATE#2026-11-22` in milliseconds since the epoch.
pub fn parse_date(s: &str) -> Result<u64, LiteralError> {
    let body = strip_prefix(s, &["DATE#", "D#"]).ok_or_else(|| syntax("expected D#.."))?;
    date_body(body).map(|days| days * MS_PER_DAY)
}

/// A time of day `TOD#12:30:15.250` or `TIME_OF_DAY#..` in milliseconds since midnight.
pub fn parse_tod(s: &str) -> Result<u64, LiteralError> {
    let body =
        strip_prefix(s, &["TIME_OF_DAY#", "TOD#"]).ok_or_else(|| syntax("expected TOD#.."))?;
    tod_body(body)
}

/// A date and time `DT#2026-11-22-12:30:15.250` or `DATE_AND_TIME#..` (UTC) in
/// milliseconds since the epoch.
pub fn parse_date_and_time(s: &str) -> Result<u64, LiteralError> {
    let body =
        strip_prefix(s, &["DATE_AND_TIME#", "DT#"]).ok_or_else(|| syntax("expected DT#.."))?;
    // The date has two dashes; the third separates it from the time of day.
    let (cut, _) = body
        .match_indices('-')
        .nth(2)
        .ok_or_else(|| syntax("expected YYYY-MM-DD-HH:MM:SS"))?;
    Ok(date_body(&body[..cut])? * MS_PER_DAY + tod_body(&body[cut + 1..])?)
}

/// `YYYY-MM-DD` as days since 1970-01-01, for years 1970 to 9999.
fn date_body(s: &str) -> Result<u64, LiteralError> {
    let mut parts = s.split('-');
    let (Some(year), Some(month), Some(day), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(syntax("expected YYYY-MM-DD"));
    };
    let year = field(year, 4, 4, "YYYY-MM-DD")?;
    let month = field(month, 1, 2, "YYYY-MM-DD")?;
    let day = field(day, 1, 2, "YYYY-MM-DD")?;
    if !(1970..=9999).contains(&year)
        || !(1..=12).contains(&month)
        || !(1..=days_in_month(year, month)).contains(&day)
    {
        return Err(Range);
    }
    // At or after 1970-01-01, so not negative.
    u64::try_from(days_from_civil(year, month, day)).map_err(|_| Range)
}

/// `HH:MM:SS` with an optional `.f`, `.ff` or `.fff`, as milliseconds.
fn tod_body(s: &str) -> Result<u64, LiteralError> {
    const FORM: &str = "HH:MM:SS.fff";
    let (hms, fraction) = match s.split_once('.') {
        Some((hms, fraction)) => (hms, Some(fraction)),
        None => (s, None),
    };
    let mut parts = hms.split(':');
    let (Some(hours), Some(minutes), Some(seconds), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(syntax(format!("expected {FORM}")));
    };
    let hours = field(hours, 1, 2, FORM)?;
    let minutes = field(minutes, 1, 2, FORM)?;
    let seconds = field(seconds, 1, 2, FORM)?;
    let ms = match fraction {
        Some(f) => {
            let digits = field(f, 1, 3, FORM)?;
            // ".250" and ".25" are 250 ms, ".2" is 200 ms.
            digits * 10i64.pow(3 - f.len() as u32)
        }
        None => 0,
    };
    if hours >= 24 || minutes >= 60 || seconds >= 60 {
        return Err(Range);
    }
    let ms = ((hours * 60 + minutes) * 60 + seconds) * 1_000 + ms;
    u64::try_from(ms).map_err(|_| Range)
}

/// A field of `min..=max` decimal digits (no sign, no `_`).
fn field(s: &str, min: usize, max: usize, form: &str) -> Result<i64, LiteralError> {
    if !(min..=max).contains(&s.len()) || !s.bytes().all(|b| b.is_ascii_digit()) {
        return Err(syntax(format!("expected {form}")));
    }
    s.parse().map_err(|_| syntax(format!("expected {form}")))
}

/// `YYYY-MM-DD` for a day number (days since 1970-01-01).
pub fn format_date(days: u64) -> String {
    // Days fit i64 for every u64 millisecond count.
    let (y, m, d) = civil_from_days(days as i64);
    format!("{y:04}-{m:02}-{d:02}")
}

/// `HH:MM:SS`, and `.mmm` when the milliseconds are not zero.
pub fn format_tod(ms: u64) -> String {
    let (seconds, millis) = (ms / 1_000, ms % 1_000);
    let hms = format!(
        "{:02}:{:02}:{:02}",
        seconds / 3_600,
        seconds / 60 % 60,
        seconds % 60
    );
    if millis == 0 {
        hms
    } else {
        format!("{hms}.{millis:03}")
    }
}

fn days_in_month(year: i64, month: i64) -> i64 {
    let leap = year % 4 == 0 && (year % 100 != 0 || year % 400 == 0);
    match month {
        2 if leap => 29,
        2 => 28,
        4 | 6 | 9 | 11 => 30,
        _ => 31,
    }
}

/// Days since 1970-01-01 of a proleptic Gregorian date (Howard Hinnant,
/// "chrono-Compatible Low-Level Date Algorithms"). Years start in March so that the
/// leap day is the last day of a year.
pub(super) fn days_from_civil(year: i64, month: i64, day: i64) -> i64 {
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let year_of_era = y - era * 400;
    let month_from_march = (month + 9) % 12;
    let day_of_year = (153 * month_from_march + 2) / 5 + day - 1;
    let day_of_era = year_of_era * 365 + year_of_era / 4 - year_of_era / 100 + day_of_year;
    era * 146_097 + day_of_era - 719_468
}

/// The inverse of [`days_from_civil`]: (year, month, day).
pub(super) fn civil_from_days(days: i64) -> (i64, i64, i64) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let day_of_era = z - era * 146_097;
    let year_of_era =
        (day_of_era - day_of_era / 1_460 + day_of_era / 36_524 - day_of_era / 146_096) / 365;
    let day_of_year = day_of_era - (365 * year_of_era + year_of_era / 4 - year_of_era / 100);
    let month_from_march = (5 * day_of_year + 2) / 153;
    let day = day_of_year - (153 * month_from_march + 2) / 5 + 1;
    let month = if month_from_march < 10 {
        month_from_march + 3
    } else {
        month_from_march - 9
    };
    let year = year_of_era + era * 400 + i64::from(month <= 2);
    (year, month, day)
}

#[cfg(test)]
mod tests {
    use serde_json::Value as Json;

    use super::super::tests::{
        decoded, fuzz_ports, is_mismatch, out_of_range, type_error, XorShift,
    };
    use super::*;
    use crate::codec::json::{decode, encode};
    use crate::codec::Message;
    use crate::types::ElementaryType as T;
    use crate::value::{TypeError, Value};

    fn time(text: &str) -> i64 {
        match decoded(&format!("{text:?}"), T::Time) {
            Value::Time(us) => us,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn time_literals_in_every_iec_spelling() {
        assert_eq!(time("T#1h2m3s4ms5us"), 3_723_004_005);
        assert_eq!(time("T#-250ms"), -250_000);
        assert_eq!(time("TIME#1.5s"), 1_500_000);
        assert_eq!(time("time#1.5S"), 1_500_000);
        assert_eq!(time("t#1d"), 86_400_000_000);
        assert_eq!(time("T#1H_30M"), 5_400_000_000);
        assert_eq!(time("T#1_000ms"), 1_000_000);
        assert_eq!(time("T#90m"), 5_400_000_000);
        assert_eq!(time("T#2000ns"), 2);
        assert_eq!(time("T#1s1000ns"), 1_000_001);
        assert_eq!(time("T#0.5d"), 43_200_000_000);
        assert_eq!(time("T#1.250000ms"), 1_250);
        assert_eq!(time("T#0s"), 0);
        assert_eq!(time("T#-0s"), 0);
        assert_eq!(decoded("-42", T::Time), Value::Time(-42));
        assert_eq!(decoded("1500000", T::Time), Value::Time(1_500_000));
    }

    #[test]
    fn bad_time_literals_are_refused() {
        for bad in [
            "T#5x",
            "T#",
            "T#-",
            "5s",
            "T#5",
            "T#1s1h",
            "T#1s1s",
            "T#1.5s2ms",
            "T#1500ns",
            "T#1.0000001us",
            "T#.5s",
            "T#5.s",
            "T#1h__2m",
            "T#1h_",
            "T#_1h",
            "T#+1s",
            "T#1 s",
            "TOD#1s",
            "T#1s ",
        ] {
            let e = type_error(&format!("{bad:?}"), T::Time);
            assert!(is_mismatch(&e), "{bad}: {e:?}");
        }
        assert_eq!(
            type_error(r#""T#106751992d""#, T::Time),
            out_of_range(T::Time, "T#106751992d")
        );
        assert!(matches!(
            type_error(&format!("\"T#{}d\"", "9".repeat(60)), T::Time),
            TypeError::OutOfRange { .. }
        ));
        assert!(matches!(
            type_error("9223372036854775808", T::Time),
            TypeError::OutOfRange { .. }
        ));
        assert!(is_mismatch(&type_error("1.5", T::Time)));
    }

    #[test]
    fn date_and_time_literals_are_validated() {
        let day = |d: u64| d * MS_PER_DAY;
        assert_eq!(
            decoded(r#""DATE#2026-11-22""#, T::Date),
            Value::Date(day(20_779))
        );
        assert_eq!(
            decoded(r#""d#2026-11-22""#, T::Date),
            Value::Date(day(20_779))
        );
        assert_eq!(
            decoded(r#""D#2000-3-1""#, T::Date),
            Value::Date(day(11_017))
        );
        assert_eq!(
            decoded(r#""TIME_OF_DAY#12:30:15.25""#, T::TimeOfDay),
            Value::TimeOfDay(45_015_250)
        );
        assert_eq!(
            decoded(r#""tod#1:2:3.4""#, T::TimeOfDay),
            Value::TimeOfDay(3_723_400)
        );
        assert_eq!(
            decoded(r#""DATE_AND_TIME#2026-11-22-12:30:15""#, T::DateAndTime),
            Value::DateAndTime(1_795_350_615_000)
        );
        for (bad, t) in [
            ("D#2026-13-01", T::Date),
            ("D#2026-00-01", T::Date),
            ("D#2026-02-30", T::Date),
            ("D#2023-02-29", T::Date),
            ("D#2100-02-29", T::Date),
            ("D#2026-04-31", T::Date),
            ("D#1969-12-31", T::Date),
            ("D#0000-01-01", T::Date),
            ("TOD#24:00:00", T::TimeOfDay),
            ("TOD#12:60:00", T::TimeOfDay),
            ("TOD#12:00:60", T::TimeOfDay),
            ("DT#2026-11-22-25:00:00", T::DateAndTime),
            ("DT#2026-02-29-00:00:00", T::DateAndTime),
        ] {
            assert_eq!(
                type_error(&format!("{bad:?}"), t),
                out_of_range(t, bad),
                "{bad}"
            );
        }
        for (bad, t) in [
            ("2026-11-22", T::Date),
            ("D#26-11-22", T::Date),
            ("D#10000-01-01", T::Date),
            ("D#2026-11", T::Date),
            ("D#2026-11-22-", T::Date),
            ("D#2026-11-+2", T::Date),
            ("D#2026/11/22", T::Date),
            ("DT#2026-11-22", T::Date),
            ("TOD#12:30", T::TimeOfDay),
            ("TOD#12:30:15.2500", T::TimeOfDay),
            ("TOD#12:30:15.", T::TimeOfDay),
            ("TOD#123:00:00", T::TimeOfDay),
            ("TOD#-1:00:00", T::TimeOfDay),
            ("TOD#12:30:15.2.5", T::TimeOfDay),
            ("T#12:30:15", T::TimeOfDay),
            ("DT#2026-11-22", T::DateAndTime),
            ("DT#2026-11-22T12:30:15", T::DateAndTime),
            ("DT#2026-11-22 12:30:15", T::DateAndTime),
            ("DT#2026-11-22--12:30:15", T::DateAndTime),
        ] {
            let e = type_error(&format!("{bad:?}"), t);
            assert!(is_mismatch(&e), "{bad}: {e:?}");
        }
        for t in [T::Date, T::TimeOfDay, T::DateAndTime] {
            assert!(is_mismatch(&type_error("0", t)), "{t}");
        }
    }

    #[test]
    fn civil_date_conversion_agrees_on_every_day() {
        let mut expected = (1970, 1, 1);
        for days in 0..=days_from_civil(9999, 12, 31) {
            assert_eq!(civil_from_days(days), expected);
            assert_eq!(days_from_civil(expected.0, expected.1, expected.2), days);
            let (y, m, d) = expected;
            let leap = y % 4 == 0 && (y % 100 != 0 || y % 400 == 0);
            let month_len = [
                31,
                if leap { 29 } else { 28 },
                31,
                30,
                31,
                30,
                31,
                31,
                30,
                31,
                30,
                31,
            ];
            expected = if d < month_len[m as usize - 1] {
                (y, m, d + 1)
            } else if m < 12 {
                (y, m + 1, 1)
            } else {
                (y + 1, 1, 1)
            };
        }
    }

    /// A valid literal with up to three random one-character edits: inputs right at
    /// the border between valid and invalid, where the literal parsers do their work.
    fn mutated_literal(rng: &mut XorShift) -> String {
        const SEEDS: [&str; 14] = [
            "T#1h2m3s4ms5us",
            "T#-250ms",
            "TIME#1.5s",
            "t#1h_30m",
            "T#2000ns",
            "D#2026-11-22",
            "DATE#2024-02-29",
            "TOD#23:59:59.999",
            "TIME_OF_DAY#12:30:15.25",
            "DT#2026-11-22-12:30:15.250",
            "16#FF",
            "2#1010",
            "8#17",
            "16#FFFF_FFFF",
        ];
        const CHARS: &[u8] = b"0123456789-:._#TtDdOoHhMmSsUuNnFfx ";
        let mut bytes = SEEDS[rng.below(SEEDS.len())].as_bytes().to_vec();
        for _ in 0..rng.below(4) {
            let at = rng.below(bytes.len() + 1);
            let c = CHARS[rng.below(CHARS.len())];
            match rng.below(3) {
                0 if at < bytes.len() => bytes[at] = c,
                1 if at < bytes.len() => {
                    bytes.remove(at);
                }
                _ => bytes.insert(at, c),
            }
        }
        String::from_utf8_lossy(&bytes).into_owned()
    }

    #[test]
    fn mutated_literals_never_panic_and_accepted_ones_round_trip() {
        let mut rng = XorShift(42);
        let ports = fuzz_ports();
        let mut accepted = 0;
        for _ in 0..2_000 {
            let text = Json::from(mutated_literal(&mut rng)).to_string();
            for port in &ports {
                if let Ok(message) = decode(text.as_bytes(), port) {
                    // Any string is a STRING; count only what a literal parser accepted.
                    if !matches!(message, Message::Data(Value::String(_))) {
                        accepted += 1;
                    }
                    let again = encode(&message, port);
                    assert_eq!(decode(&again, port), Ok(message), "{text}");
                }
            }
        }
        assert!(
            accepted > 100,
            "only {accepted} mutated literals were valid"
        );
    }
}
