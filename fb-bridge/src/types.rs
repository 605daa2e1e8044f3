//! IEC 61131-3 data types a port can carry: the elementary types and `ARRAY [n] OF` one.
//!
//! Types are written the way IEC 61131-3 and 4diac write them (`INT`, `ARRAY [4] OF REAL`)
//! both in declarations and in error messages, so a device author reads the same words
//! in their FB editor and in fbbus's answers.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// The elementary types. The discriminant is the IEC 61499 compliance-profile (`fbdk`)
/// type number, so the codec's tag byte is `0x40 | type as u8`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum ElementaryType {
    Bool = 1,
    Sint = 2,
    Int = 3,
    Dint = 4,
    Lint = 5,
    Usint = 6,
    Uint = 7,
    Udint = 8,
    Ulint = 9,
    Real = 10,
    Lreal = 11,
    Time = 12,
    Date = 13,
    TimeOfDay = 14,
    DateAndTime = 15,
    String = 16,
    Byte = 17,
    Word = 18,
    Dword = 19,
    Lword = 20,
    WString = 21,
}

impl ElementaryType {
    pub const ALL: [ElementaryType; 21] = [
        Self::Bool,
        Self::Sint,
        Self::Int,
        Self::Dint,
        Self::Lint,
        Self::Usint,
        Self::Uint,
        Self::Udint,
        Self::Ulint,
        Self::Real,
        Self::Lreal,
        Self::Time,
        Self::Date,
        Self::TimeOfDay,
        Self::DateAndTime,
        Self::String,
        Self::Byte,
        Self::Word,
        Self::Dword,
        Self::Lword,
        Self::WString,
    ];

    /// The IEC 61131-3 name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Bool => "BOOL",
            Self::Sint => "SINT",
            Self::Int => "INT",
            Self::Dint => "DINT",
            Self::Lint => "LINT",
            Self::Usint => "USINT",
            Self::Uint => "UINT",
            Self::Udint => "UDINT",
            Self::Ulint => "ULINT",
            Self::Real => "REAL",
            Self::Lreal => "LREAL",
            Self::Time => "TIME",
            Self::Date => "DATE",
            Self::TimeOfDay => "TIME_OF_DAY",
            Self::DateAndTime => "DATE_AND_TIME",
            Self::String => "STRING",
            Self::Byte => "BYTE",
            Self::Word => "WORD",
            Self::Dword => "DWORD",
            Self::Lword => "LWORD",
            Self::WString => "WSTRING",
        }
    }

    /// The compliance-profile type number (`fbdk` tag is `0x40 | number`).
    pub fn number(self) -> u8 {
        self as u8
    }

    /// Whether canonical JSON has the only form the decoder accepts for this type, so an
    /// accepted JSON value is already canonical. Not so for the bit strings (which also
    /// accept `"16#FF"`), the time types (several literal spellings), the reals (`1e0`,
    /// `1.00`, `-0.0`, and for `REAL` values that round to another `f32`, such as `1e-50`
    /// to 0: every encoding must carry the one value the port holds) and `BOOL` (`1`/`0`
    /// for `true`/`false`).
    pub fn has_one_json_form(self) -> bool {
        !matches!(
            self,
            Self::Bool
                | Self::Real
                | Self::Lreal
                | Self::Byte
                | Self::Word
                | Self::Dword
                | Self::Lword
                | Self::Time
                | Self::Date
                | Self::TimeOfDay
                | Self::DateAndTime
        )
    }

    /// Whether a value of this type reads as a number: the integers, bit strings and reals,
    /// and BOOL (1/0). Not the strings, nor the time types (text literals).
    pub fn reads_as_number(self) -> bool {
        !matches!(
            self,
            Self::String
                | Self::WString
                | Self::Time
                | Self::Date
                | Self::TimeOfDay
                | Self::DateAndTime
        )
    }

    pub fn from_number(n: u8) -> Option<ElementaryType> {
        Self::ALL.into_iter().find(|t| t.number() == n)
    }
}

impl fmt::Display for ElementaryType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A type name that is not one fbbus knows.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown type '{0}': expected an IEC 61131-3 elementary type (BOOL, INT, REAL, STRING, TIME, ...) or ARRAY [n] OF one")]
pub struct UnknownType(pub String);

impl FromStr for ElementaryType {
    type Err = UnknownType;

    fn from_str(s: &str) -> Result<Self, UnknownType> {
        let upper = s.trim().to_ascii_uppercase();
        // IEC 61131-3 short forms.
        let name = match upper.as_str() {
            "TOD" => "TIME_OF_DAY",
            "DT" => "DATE_AND_TIME",
            other => other,
        };
        Self::ALL
            .into_iter()
            .find(|t| t.name() == name)
            .ok_or_else(|| UnknownType(s.to_owned()))
    }
}

/// Largest array a port may declare: the `fbdk` encoding counts elements in two bytes.
pub const MAX_ARRAY_LEN: usize = 65_535;

/// The type of one data port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DataType {
    Elementary(ElementaryType),
    /// `ARRAY [n] OF t`: exactly `n` elements, 1 <= n <= [`MAX_ARRAY_LEN`].
    Array(ElementaryType, u16),
}

impl DataType {
    /// The elementary type of the value, or of each element of an array.
    pub fn element(self) -> ElementaryType {
        match self {
            DataType::Elementary(t) | DataType::Array(t, _) => t,
        }
    }

    /// See [`ElementaryType::has_one_json_form`].
    pub fn has_one_json_form(self) -> bool {
        match self {
            DataType::Elementary(t) | DataType::Array(t, _) => t.has_one_json_form(),
        }
    }
}

impl fmt::Display for DataType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DataType::Elementary(t) => write!(f, "{t}"),
            DataType::Array(t, n) => write!(f, "ARRAY [{n}] OF {t}"),
        }
    }
}

impl FromStr for DataType {
    type Err = UnknownType;

    /// Accepts `INT`, `ARRAY [4] OF INT`, `ARRAY[0..3] OF INT` (IEC subrange: 4 elements).
    fn from_str(s: &str) -> Result<Self, UnknownType> {
        let unknown = || UnknownType(s.to_owned());
        let trimmed = s.trim();
        let upper = trimmed.to_ascii_uppercase();
        let Some(rest) = upper.strip_prefix("ARRAY") else {
            return trimmed.parse().map(DataType::Elementary);
        };
        let rest = rest.trim_start();
        let rest = rest.strip_prefix('[').ok_or_else(unknown)?;
        let (bounds, rest) = rest.split_once(']').ok_or_else(unknown)?;
        let element = rest.trim_start().strip_prefix("OF").ok_or_else(unknown)?;
        if !element.starts_with(char::is_whitespace) {
            return Err(unknown());
        }
        let element: ElementaryType = element.trim().parse().map_err(|_| unknown())?;
        let bounds = bounds.trim();
        let len: usize = match bounds.split_once("..") {
            Some((lo, hi)) => {
                let lo: i64 = lo.trim().parse().map_err(|_| unknown())?;
                let hi: i64 = hi.trim().parse().map_err(|_| unknown())?;
                // Checked: `hi - lo + 1` overflowed for bounds far apart, a panic with
                // overflow checks on (found by broker/fuzz `declaration`).
                let len = hi.checked_sub(lo).and_then(|n| n.checked_add(1));
                usize::try_from(len.ok_or_else(unknown)?).map_err(|_| unknown())?
            }
            None => bounds.parse().map_err(|_| unknown())?,
        };
        if len == 0 || len > MAX_ARRAY_LEN {
            return Err(UnknownType(format!(
                "{trimmed} (an array has 1 to {MAX_ARRAY_LEN} elements)"
            )));
        }
        Ok(DataType::Array(element, len as u16))
    }
}

impl Serialize for DataType {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for DataType {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_elementary_name_round_trips() {
        for t in ElementaryType::ALL {
            assert_eq!(t.name().parse::<ElementaryType>(), Ok(t));
            assert_eq!(ElementaryType::from_number(t.number()), Some(t));
        }
        assert_eq!("tod".parse(), Ok(ElementaryType::TimeOfDay));
        assert_eq!("DT".parse(), Ok(ElementaryType::DateAndTime));
        assert!("FLOAT".parse::<ElementaryType>().is_err());
    }

    #[test]
    fn arrays_parse_in_both_forms() {
        assert_eq!(
            "ARRAY [4] OF INT".parse(),
            Ok(DataType::Array(ElementaryType::Int, 4))
        );
        assert_eq!(
            "array[0..3] of real".parse(),
            Ok(DataType::Array(ElementaryType::Real, 4))
        );
        assert_eq!(
            DataType::Array(ElementaryType::Bool, 2).to_string(),
            "ARRAY [2] OF BOOL"
        );
        for bad in [
            "ARRAY [0] OF INT",
            "ARRAY [70000] OF INT",
            "ARRAY [4] INT",
            "ARRAY [4] OFINT",
            "ARRAY [4] OF ARRAY [2] OF INT",
            "ARRAY 4 OF INT",
        ] {
            assert!(bad.parse::<DataType>().is_err(), "{bad}");
        }
    }

    /// Regression (broker/fuzz/regressions/declaration): subrange bounds far apart are
    /// refused, not an arithmetic overflow.
    #[test]
    fn subrange_bounds_never_overflow() {
        for bad in [
            "ARRAY [-2..9223372036854775807] OF INT",
            "ARRAY [-9223372036854775808..9223372036854775807] OF INT",
            "ARRAY [9223372036854775807..-9223372036854775808] OF INT",
            "ARRAY [0..-2] OF INT",
        ] {
            assert!(bad.parse::<DataType>().is_err(), "{bad}");
        }
        assert_eq!(
            "ARRAY [-1..2] OF INT".parse(),
            Ok(DataType::Array(ElementaryType::Int, 4))
        );
    }
}
