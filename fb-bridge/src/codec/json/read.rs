//! What one JSON value means as an IEC type: the reading both decoders share.
//!
//! The streaming decoder (`de`) and the tree ([`value_from_json`], and the reference
//! decoder `tree`) both hand each JSON value over as a [`Token`] and read it here, so they
//! accept and refuse the same values with the same errors. The strictness table is the
//! module documentation of `codec::json`.

use serde_json::{Map, Value as Json};

use super::iec::{self, excerpt};
use crate::codec::CodecError;
use crate::types::{DataType, ElementaryType};
use crate::value::{TypeError, Value};

/// Reads a value of type `ty` from its JSON form (the table in this module's
/// documentation), then checks it with [`Value::check`].
pub fn value_from_json(j: &Json, ty: DataType) -> Result<Value, TypeError> {
    let value = match ty {
        DataType::Elementary(t) => scalar_from_token(Token::of(j), t)?,
        DataType::Array(t, n) => array_from_json(j, t, n)?,
    };
    value.check(ty)?;
    Ok(value)
}

/// Reads exactly the named, typed `fields` from a JSON object, in their order: what
/// `de` does for an object whose fields do not all have distinct names.
///
/// Structural mistakes are reported before value mistakes: a missing field first (in
/// field order), then a key that is not a field, then the first ill-typed value.
pub(super) fn object_fields(
    object: &Map<String, Json>,
    fields: &[(&str, DataType)],
) -> Result<Vec<Value>, CodecError> {
    if let Some((name, _)) = fields.iter().find(|(name, _)| !object.contains_key(*name)) {
        return Err(CodecError::Missing((*name).to_owned()));
    }
    if let Some(key) = object
        .keys()
        .find(|key| !fields.iter().any(|(name, _)| name == key))
    {
        return Err(CodecError::Unexpected(key.clone()));
    }
    fields
        .iter()
        .map(|(name, ty)| {
            let value = object.get(*name).unwrap_or(&Json::Null);
            value_from_json(value, *ty).map_err(|error| CodecError::Type {
                port: (*name).to_owned(),
                error,
            })
        })
        .collect()
}

/// One JSON value as the value readers see it: a scalar with its content, an array or
/// an object by kind only. Both decoders, the tree ([`value_from_json`]) and the stream
/// (`de`), hand values over as tokens, so they read them identically.
#[derive(Debug, Clone, Copy)]
pub(super) enum Token<'a> {
    Null,
    Bool(bool),
    /// An integer that `serde_json` read exactly: it fits `i64` or `u64`.
    Int(i128),
    /// Any other number: it has a fraction or an exponent, or is an integer beyond 64
    /// bits.
    Float(f64),
    Str(&'a str),
    Array,
    Object,
}

impl<'a> Token<'a> {
    pub(super) fn of(j: &'a Json) -> Token<'a> {
        match j {
            Json::Null => Token::Null,
            Json::Bool(b) => Token::Bool(*b),
            Json::Number(n) => match (n.as_i64(), n.as_u64()) {
                (Some(i), _) => Token::Int(i.into()),
                (None, Some(u)) => Token::Int(u.into()),
                (None, None) => Token::Float(n.as_f64().unwrap_or(f64::NAN)),
            },
            Json::String(s) => Token::Str(s),
            Json::Array(_) => Token::Array,
            Json::Object(_) => Token::Object,
        }
    }

    /// What kind of JSON value this is, for error messages ("expected INT, got a JSON
    /// string").
    pub(super) fn describe(self) -> &'static str {
        match self {
            Token::Null => "null",
            Token::Bool(_) => "a JSON boolean",
            Token::Int(_) => "a JSON integer",
            Token::Float(x) if x.fract() != 0.0 => "a JSON number with a fraction",
            Token::Float(_) => "a JSON number with a fraction or exponent",
            Token::Str(_) => "a JSON string",
            Token::Array => "a JSON array",
            Token::Object => "a JSON object",
        }
    }

    /// A number as `serde_json` writes it.
    fn number_text(self) -> String {
        match self {
            Token::Int(n) => n.to_string(),
            Token::Float(x) => Json::from(x).to_string(),
            other => other.describe().to_owned(),
        }
    }
}

pub(super) fn mismatch(token: Token<'_>, expected: DataType) -> TypeError {
    TypeError::Mismatch {
        expected,
        got: token.describe().to_owned(),
    }
}

fn scalar_mismatch(token: Token<'_>, t: ElementaryType) -> TypeError {
    mismatch(token, DataType::Elementary(t))
}

fn array_from_json(j: &Json, t: ElementaryType, n: u16) -> Result<Value, TypeError> {
    let Some(items) = j.as_array() else {
        return Err(mismatch(Token::of(j), DataType::Array(t, n)));
    };
    if items.len() != usize::from(n) {
        return Err(TypeError::ArrayLength {
            expected: usize::from(n),
            got: items.len(),
        });
    }
    let elements = items
        .iter()
        .enumerate()
        .map(|(index, item)| {
            scalar_from_token(Token::of(item), t).map_err(|error| TypeError::Element {
                index,
                error: Box::new(error),
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Value::Array(t, elements))
}

/// Reads an elementary value of type `t` (not yet [checked](Value::check)).
pub(super) fn scalar_from_token(token: Token<'_>, t: ElementaryType) -> Result<Value, TypeError> {
    use ElementaryType as T;
    Ok(match t {
        T::Bool => Value::Bool(boolean(token)?),
        T::Sint => Value::Sint(fit(integer(token, t)?, t)?),
        T::Int => Value::Int(fit(integer(token, t)?, t)?),
        T::Dint => Value::Dint(fit(integer(token, t)?, t)?),
        T::Lint => Value::Lint(fit(integer(token, t)?, t)?),
        T::Usint => Value::Usint(fit(integer(token, t)?, t)?),
        T::Uint => Value::Uint(fit(integer(token, t)?, t)?),
        T::Udint => Value::Udint(fit(integer(token, t)?, t)?),
        T::Ulint => Value::Ulint(fit(integer(token, t)?, t)?),
        T::Byte => Value::Byte(fit(bit_string(token, t)?, t)?),
        T::Word => Value::Word(fit(bit_string(token, t)?, t)?),
        T::Dword => Value::Dword(fit(bit_string(token, t)?, t)?),
        T::Lword => Value::Lword(fit(bit_string(token, t)?, t)?),
        T::Real => Value::Real(real(token)?),
        T::Lreal => Value::Lreal(number(token, t)?),
        T::String => Value::String(string(token, t)?),
        T::WString => Value::WString(string(token, t)?),
        T::Time => Value::Time(time(token)?),
        T::Date => Value::Date(literal(token, t, iec::parse_date)?),
        T::TimeOfDay => Value::TimeOfDay(literal(token, t, iec::parse_tod)?),
        T::DateAndTime => Value::DateAndTime(literal(token, t, iec::parse_date_and_time)?),
    })
}

/// A JSON integer, exactly. `serde_json` keeps integers that fit `i64` or `u64` as such;
/// anything else it reads is an `f64`: a fraction, an exponent, or an integer too large
/// for 64 bits (that last one is out of range rather than of the wrong kind).
fn integer(token: Token<'_>, t: ElementaryType) -> Result<i128, TypeError> {
    match token {
        Token::Int(n) => Ok(n),
        // `-0` is a JSON integer, but `serde_json` reads it as the float -0.0 to keep its
        // sign (issue 21: it was refused). Every spelling it reads that way (`-0`, `-0.0`,
        // `-0e0`) is the integer 0.
        Token::Float(x) if x == 0.0 && x.is_sign_negative() => Ok(0),
        Token::Float(x) => {
            // Integers just below i64::MIN round to exactly -2^63, so that counts as beyond.
            let beyond_64_bits = x <= -(2f64.powi(63)) || x >= 2f64.powi(64);
            if x.fract() == 0.0 && beyond_64_bits {
                return Err(TypeError::OutOfRange {
                    ty: t,
                    value: token.number_text(),
                });
            }
            Err(scalar_mismatch(token, t))
        }
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// A `BOOL`: `true`/`false`, or the integers `1`/`0` that PLC code and people write
/// (IEC 61131-3 itself reads `BOOL#1` and `BOOL#0`; issue 35). Any other integer is out
/// of range; `1.0` or `"1"` are of the wrong kind, as for the integer types.
fn boolean(token: Token<'_>) -> Result<bool, TypeError> {
    let t = ElementaryType::Bool;
    match token {
        Token::Bool(b) => Ok(b),
        Token::Int(1) => Ok(true),
        Token::Int(0) => Ok(false),
        Token::Int(_) => Err(TypeError::OutOfRange {
            ty: t,
            value: token.number_text(),
        }),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// Narrows an integer to the Rust type of `t`'s values.
fn fit<N: TryFrom<i128>>(n: i128, t: ElementaryType) -> Result<N, TypeError> {
    N::try_from(n).map_err(|_| TypeError::OutOfRange {
        ty: t,
        value: n.to_string(),
    })
}

/// A bit string (`BYTE` .. `LWORD`): an integer, or an IEC literal such as `"16#FF"`.
fn bit_string(token: Token<'_>, t: ElementaryType) -> Result<i128, TypeError> {
    match token {
        Token::Str(s) => literal_str(s, t, iec::parse_bit_string),
        _ => integer(token, t),
    }
}

fn number(token: Token<'_>, t: ElementaryType) -> Result<f64, TypeError> {
    match token {
        // Rounds to nearest, as `serde_json::Number::as_f64` does.
        Token::Int(n) => Ok(n as f64),
        Token::Float(x) => Ok(x),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// A `REAL`: any number that rounds to a finite `f32`. Rounding rather than comparing
/// with `f32::MAX` accepts `3.4028235e38`, the shortest decimal for `f32::MAX`, which is
/// a little larger than it.
fn real(token: Token<'_>) -> Result<f32, TypeError> {
    let x = number(token, ElementaryType::Real)?;
    let narrowed = x as f32;
    if narrowed.is_finite() {
        Ok(narrowed)
    } else {
        Err(TypeError::OutOfRange {
            ty: ElementaryType::Real,
            value: token.number_text(),
        })
    }
}

fn string(token: Token<'_>, t: ElementaryType) -> Result<String, TypeError> {
    match token {
        Token::Str(s) => Ok(s.to_owned()),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// A `TIME`: an IEC literal, or an integer number of microseconds.
fn time(token: Token<'_>) -> Result<i64, TypeError> {
    let t = ElementaryType::Time;
    match token {
        Token::Str(s) => literal_str(s, t, iec::parse_time),
        _ => fit(integer(token, t)?, t),
    }
}

/// A JSON string holding an IEC literal of type `t`, read by `parse`.
fn literal<V>(
    token: Token<'_>,
    t: ElementaryType,
    parse: impl Fn(&str) -> Result<V, iec::LiteralError>,
) -> Result<V, TypeError> {
    match token {
        Token::Str(s) => literal_str(s, t, parse),
        _ => Err(scalar_mismatch(token, t)),
    }
}

/// An IEC literal of type `t` in `s`, read by `parse`.
fn literal_str<V>(
    s: &str,
    t: ElementaryType,
    parse: impl Fn(&str) -> Result<V, iec::LiteralError>,
) -> Result<V, TypeError> {
    parse(s).map_err(|e| match e {
        iec::LiteralError::Syntax(why) => TypeError::Mismatch {
            expected: DataType::Elementary(t),
            got: format!("the string {} ({why})", Json::from(excerpt(s))),
        },
        iec::LiteralError::Range => TypeError::OutOfRange {
            ty: t,
            value: excerpt(s),
        },
    })
}

#[cfg(test)]
mod tests {
    use super::super::tests::{decoded, is_mismatch, out_of_range, type_error};
    use super::*;
    use crate::types::ElementaryType as T;

    #[test]
    fn minus_zero_is_the_integer_zero() {
        use crate::codec::json::tests::decode_text;
        for t in [
            T::Sint,
            T::Int,
            T::Dint,
            T::Lint,
            T::Usint,
            T::Ulint,
            T::Byte,
        ] {
            let m = decode_text("-0", DataType::Elementary(t)).expect("-0 is an integer");
            let zero = decode_text("0", DataType::Elementary(t)).unwrap();
            assert_eq!(m, zero, "{t}");
        }
    }

    #[test]
    fn integers_are_strict_about_range_and_kind() {
        assert_eq!(type_error("128", T::Sint), out_of_range(T::Sint, "128"));
        assert_eq!(type_error("300", T::Sint), out_of_range(T::Sint, "300"));
        assert_eq!(type_error("-1", T::Usint), out_of_range(T::Usint, "-1"));
        assert_eq!(type_error("256", T::Byte), out_of_range(T::Byte, "256"));
        assert_eq!(
            type_error("-9223372036854775809", T::Lint),
            out_of_range(T::Lint, "-9.223372036854776e+18")
        );
        assert!(matches!(
            type_error("18446744073709551616", T::Ulint),
            TypeError::OutOfRange { ty: T::Ulint, .. }
        ));
        assert_eq!(
            type_error(r#""5""#, T::Int),
            TypeError::Mismatch {
                expected: DataType::Elementary(T::Int),
                got: "a JSON string".into()
            }
        );
        assert_eq!(
            type_error("1.5", T::Dint),
            TypeError::Mismatch {
                expected: DataType::Elementary(T::Dint),
                got: "a JSON number with a fraction".into()
            }
        );
        for (text, t) in [
            ("3.0", T::Int),
            ("1e3", T::Uint),
            ("null", T::Lint),
            ("true", T::Sint),
            ("[1]", T::Ulint),
            ("{}", T::Udint),
            ("1.0", T::Bool),
            (r#""1""#, T::Bool),
            (r#""true""#, T::Bool),
        ] {
            assert!(is_mismatch(&type_error(text, t)), "{text} as {t}");
        }
    }

    #[test]
    fn bool_accepts_one_and_zero_as_plc_code_writes_them() {
        use crate::codec::json::{encode, tests::decode_text};
        use crate::codec::Message;
        assert_eq!(decoded("1", T::Bool), Value::Bool(true));
        assert_eq!(decoded("0", T::Bool), Value::Bool(false));
        assert_eq!(type_error("2", T::Bool), out_of_range(T::Bool, "2"));
        assert_eq!(type_error("-1", T::Bool), out_of_range(T::Bool, "-1"));
        // Written back in the canonical form: JSON booleans.
        let ty = DataType::Array(T::Bool, 3);
        let port = crate::interface::OutputPort::Data(ty);
        let message = decode_text("[1, 0, true]", ty).unwrap();
        assert_eq!(
            message,
            Message::Data(Value::Array(
                T::Bool,
                vec![Value::Bool(true), Value::Bool(false), Value::Bool(true)]
            ))
        );
        assert_eq!(encode(&message, &port), b"[true,false,true]");
        // The tree reader agrees with the streaming one.
        assert_eq!(
            value_from_json(&serde_json::json!(1), DataType::Elementary(T::Bool)),
            Ok(Value::Bool(true))
        );
    }

    #[test]
    fn bit_strings_accept_iec_based_literals() {
        assert_eq!(decoded(r#""16#FF""#, T::Byte), Value::Byte(255));
        assert_eq!(decoded(r#""16#ff""#, T::Byte), Value::Byte(255));
        assert_eq!(decoded(r#""2#1010""#, T::Byte), Value::Byte(10));
        assert_eq!(decoded(r#""8#17""#, T::Word), Value::Word(15));
        assert_eq!(
            decoded(r#""16#FFFF_FFFF""#, T::Dword),
            Value::Dword(u32::MAX)
        );
        assert_eq!(
            decoded(r#""16#FFFF_FFFF_FFFF_FFFF""#, T::Lword),
            Value::Lword(u64::MAX)
        );
        assert_eq!(decoded("65535", T::Word), Value::Word(65535));
        assert_eq!(
            type_error(r#""16#100""#, T::Byte),
            out_of_range(T::Byte, "256")
        );
        assert_eq!(
            type_error(r#""16#1_0000_0000_0000_0000""#, T::Lword),
            out_of_range(T::Lword, "18446744073709551616")
        );
        let beyond_u128 = format!("16#{}", "F".repeat(33));
        assert_eq!(
            type_error(&format!("{beyond_u128:?}"), T::Lword),
            out_of_range(T::Lword, &beyond_u128)
        );
        for bad in [
            r#""FF""#,
            r#""16#""#,
            r#""16#FG""#,
            r#""16#_FF""#,
            r#""16#F__F""#,
            r#""2#102""#,
            r#""10#5""#,
            r#""-16#1""#,
            r#""255""#,
        ] {
            assert!(is_mismatch(&type_error(bad, T::Byte)), "{bad}");
        }
        // Only bit strings take based literals.
        assert!(is_mismatch(&type_error(r#""16#FF""#, T::Usint)));
    }

    #[test]
    fn reals_must_fit_their_width() {
        assert_eq!(decoded("1", T::Real), Value::Real(1.0));
        assert_eq!(decoded("-7", T::Lreal), Value::Lreal(-7.0));
        assert_eq!(
            decoded("18446744073709551615", T::Lreal),
            Value::Lreal(1.8446744073709552e19)
        );
        assert_eq!(decoded("1e-60", T::Real), Value::Real(0.0));
        assert_eq!(type_error("1e39", T::Real), out_of_range(T::Real, "1e+39"));
        assert_eq!(
            type_error("-3.5e38", T::Real),
            out_of_range(T::Real, "-3.5e+38")
        );
        assert!(is_mismatch(&type_error(r#""1.0""#, T::Lreal)));
        assert!(is_mismatch(&type_error("null", T::Real)));
    }

    #[test]
    fn strings_are_json_strings_within_their_length() {
        assert!(is_mismatch(&type_error("5", T::String)));
        assert!(is_mismatch(&type_error("null", T::WString)));
        let long = Json::from("x".repeat(65_536)).to_string();
        assert_eq!(type_error(&long, T::String), TypeError::TooLong(T::String));
    }

    #[test]
    fn arrays_need_their_exact_length_and_element_type() {
        let ty = DataType::Array(T::Int, 3);
        assert_eq!(
            type_error("[1,2]", ty),
            TypeError::ArrayLength {
                expected: 3,
                got: 2
            }
        );
        assert_eq!(
            type_error("[1,2,3,4]", ty),
            TypeError::ArrayLength {
                expected: 3,
                got: 4
            }
        );
        assert_eq!(
            type_error("[1,40000,3]", ty),
            TypeError::Element {
                index: 1,
                error: Box::new(out_of_range(T::Int, "40000"))
            }
        );
        assert!(is_mismatch(&type_error("5", ty)));
        assert!(is_mismatch(&type_error(r#"{"0":1}"#, ty)));
        assert!(is_mismatch(&type_error("[1,2,3]", T::Int)));
        assert!(matches!(
            type_error(r#"["T#1s","T#1y"]"#, DataType::Array(T::Time, 2)),
            TypeError::Element { index: 1, .. }
        ));
    }

    #[test]
    fn long_strings_are_shortened_in_errors() {
        let text = format!("\"T#{}\"", "x".repeat(1_000));
        let message = type_error(&text, T::Time).to_string();
        assert!(message.len() < 200, "{message}");
    }
}
