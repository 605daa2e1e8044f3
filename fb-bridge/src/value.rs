//! Typed values: what a data port holds, as Rust values rather than JSON text.
//!
//! Each variant holds exactly the range of its IEC 61131-3 type, so most range checks are
//! done by the Rust type itself; [`Value::check`] adds the rest (array lengths, string
//! lengths, times of day). Times and dates are integers in fixed units, the same in every
//! codec:
//!
//! | type | unit |
//! |---|---|
//! | `TIME` | signed microseconds (the `fbdk` unit) |
//! | `DATE` | milliseconds since 1970-01-01 UTC, a multiple of one day |
//! | `TIME_OF_DAY` | milliseconds since midnight, below 86,400,000 |
//! | `DATE_AND_TIME` | milliseconds since 1970-01-01 00:00 UTC |

use crate::types::{DataType, ElementaryType};

pub const MS_PER_DAY: u64 = 86_400_000;

/// The last millisecond of 9999-12-31, the end of the IEC literal range (`DT#9999-...`).
pub const MAX_DATE_AND_TIME_MS: u64 = 253_402_300_799_999;

/// Longest STRING (bytes) or WSTRING (UTF-16 units): `fbdk` counts them in two bytes.
pub const MAX_STRING_LEN: usize = 65_535;

#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Bool(bool),
    Sint(i8),
    Int(i16),
    Dint(i32),
    Lint(i64),
    Usint(u8),
    Uint(u16),
    Udint(u32),
    Ulint(u64),
    Real(f32),
    Lreal(f64),
    Byte(u8),
    Word(u16),
    Dword(u32),
    Lword(u64),
    String(String),
    WString(String),
    /// Microseconds.
    Time(i64),
    /// Milliseconds since the epoch, at midnight UTC.
    Date(u64),
    /// Milliseconds since midnight.
    TimeOfDay(u64),
    /// Milliseconds since the epoch.
    DateAndTime(u64),
    /// Elements all of the given type (never themselves arrays).
    Array(ElementaryType, Vec<Value>),
}

/// Why a value does not fit a port's type.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TypeError {
    #[error("expected {expected}, got {got}")]
    Mismatch { expected: DataType, got: String },
    #[error("{value} is out of range for {ty}")]
    OutOfRange { ty: ElementaryType, value: String },
    #[error("expected {expected} elements, got {got}")]
    ArrayLength { expected: usize, got: usize },
    #[error("element {index}: {error}")]
    Element { index: usize, error: Box<TypeError> },
    #[error("{0} is longer than {MAX_STRING_LEN} units")]
    TooLong(ElementaryType),
    /// A NUL character: 4diac FORTE and other C runtimes end a string there, so one
    /// message would mean two values (issue 21). Refused in every encoding.
    #[error("{0} contains a NUL character, which C runtimes (4diac FORTE) take as its end")]
    Nul(ElementaryType),
}

impl Value {
    /// The elementary type of a scalar value; for an array, its element type.
    pub fn elementary_type(&self) -> ElementaryType {
        use ElementaryType as T;
        match self {
            Value::Bool(_) => T::Bool,
            Value::Sint(_) => T::Sint,
            Value::Int(_) => T::Int,
            Value::Dint(_) => T::Dint,
            Value::Lint(_) => T::Lint,
            Value::Usint(_) => T::Usint,
            Value::Uint(_) => T::Uint,
            Value::Udint(_) => T::Udint,
            Value::Ulint(_) => T::Ulint,
            Value::Real(_) => T::Real,
            Value::Lreal(_) => T::Lreal,
            Value::Byte(_) => T::Byte,
            Value::Word(_) => T::Word,
            Value::Dword(_) => T::Dword,
            Value::Lword(_) => T::Lword,
            Value::String(_) => T::String,
            Value::WString(_) => T::WString,
            Value::Time(_) => T::Time,
            Value::Date(_) => T::Date,
            Value::TimeOfDay(_) => T::TimeOfDay,
            Value::DateAndTime(_) => T::DateAndTime,
            Value::Array(t, _) => *t,
        }
    }

    /// The value's data type (arrays report their actual length).
    pub fn data_type(&self) -> DataType {
        match self {
            Value::Array(t, items) => {
                DataType::Array(*t, items.len().min(u16::MAX as usize) as u16)
            }
            scalar => DataType::Elementary(scalar.elementary_type()),
        }
    }

    /// Checks that this value is a valid value of `ty`: same type, and within the ranges
    /// the Rust representation does not already enforce.
    pub fn check(&self, ty: DataType) -> Result<(), TypeError> {
        match (ty, self) {
            (DataType::Elementary(t), scalar) if !matches!(scalar, Value::Array(..)) => {
                if scalar.elementary_type() != t {
                    return Err(TypeError::Mismatch {
                        expected: ty,
                        got: scalar.elementary_type().to_string(),
                    });
                }
                scalar.check_scalar()
            }
            (DataType::Array(t, n), Value::Array(et, items)) => {
                if *et != t {
                    return Err(TypeError::Mismatch {
                        expected: ty,
                        got: format!("ARRAY OF {et}"),
                    });
                }
                if items.len() != n as usize {
                    return Err(TypeError::ArrayLength {
                        expected: n as usize,
                        got: items.len(),
                    });
                }
                for (index, item) in items.iter().enumerate() {
                    item.check(DataType::Elementary(t))
                        .map_err(|e| TypeError::Element {
                            index,
                            error: Box::new(e),
                        })?;
                }
                Ok(())
            }
            (_, other) => Err(TypeError::Mismatch {
                expected: ty,
                got: other.data_type().to_string(),
            }),
        }
    }

    fn check_scalar(&self) -> Result<(), TypeError> {
        let out_of_range = |v: String| {
            Err(TypeError::OutOfRange {
                ty: self.elementary_type(),
                value: v,
            })
        };
        match self {
            Value::String(s) if s.len() > MAX_STRING_LEN => {
                Err(TypeError::TooLong(ElementaryType::String))
            }
            Value::String(s) if s.contains('\0') => Err(TypeError::Nul(ElementaryType::String)),
            Value::WString(s) if s.contains('\0') => Err(TypeError::Nul(ElementaryType::WString)),
            Value::WString(s) if s.encode_utf16().count() > MAX_STRING_LEN => {
                Err(TypeError::TooLong(ElementaryType::WString))
            }
            Value::Date(ms) if ms % MS_PER_DAY != 0 => {
                out_of_range(format!("{ms} ms (not midnight)"))
            }
            Value::TimeOfDay(ms) if *ms >= MS_PER_DAY => out_of_range(format!("{ms} ms")),
            Value::Date(ms) | Value::DateAndTime(ms) if *ms > MAX_DATE_AND_TIME_MS => {
                out_of_range(format!("{ms} ms (after 9999-12-31)"))
            }
            Value::Real(x) if !x.is_finite() => out_of_range(x.to_string()),
            Value::Lreal(x) if !x.is_finite() => out_of_range(x.to_string()),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ElementaryType as T;

    #[test]
    fn strings_with_nul_are_refused() {
        for (v, t) in [
            (Value::String("a\0b".into()), T::String),
            (Value::WString("\0".into()), T::WString),
        ] {
            assert_eq!(v.check(DataType::Elementary(t)), Err(TypeError::Nul(t)));
        }
        assert!(Value::String("ab".into())
            .check(DataType::Elementary(T::String))
            .is_ok());
    }

    #[test]
    fn check_accepts_the_declared_type_only() {
        assert!(Value::Int(5).check(DataType::Elementary(T::Int)).is_ok());
        assert!(matches!(
            Value::Dint(5).check(DataType::Elementary(T::Int)),
            Err(TypeError::Mismatch { .. })
        ));
        let arr = Value::Array(T::Int, vec![Value::Int(1), Value::Int(2)]);
        assert!(arr.check(DataType::Array(T::Int, 2)).is_ok());
        assert_eq!(
            arr.check(DataType::Array(T::Int, 3)),
            Err(TypeError::ArrayLength {
                expected: 3,
                got: 2
            })
        );
        let mixed = Value::Array(T::Int, vec![Value::Int(1), Value::Bool(true)]);
        assert!(matches!(
            mixed.check(DataType::Array(T::Int, 2)),
            Err(TypeError::Element { index: 1, .. })
        ));
    }

    #[test]
    fn check_enforces_ranges_the_representation_does_not() {
        let tod = DataType::Elementary(T::TimeOfDay);
        assert!(Value::TimeOfDay(MS_PER_DAY - 1).check(tod).is_ok());
        assert!(Value::TimeOfDay(MS_PER_DAY).check(tod).is_err());
        assert!(Value::Date(MS_PER_DAY * 3)
            .check(DataType::Elementary(T::Date))
            .is_ok());
        assert!(Value::Date(5).check(DataType::Elementary(T::Date)).is_err());
        assert!(Value::Real(f32::NAN)
            .check(DataType::Elementary(T::Real))
            .is_err());
        let long = Value::String("x".repeat(MAX_STRING_LEN + 1));
        assert!(long.check(DataType::Elementary(T::String)).is_err());
    }
}
