//! DATE, TIME_OF_DAY and DATE_AND_TIME between the wire's unit ([`TimeUnit`]) and the
//! milliseconds [`Value`] holds: both directions of the codec need it, and the rules (a
//! sub-millisecond time truncated, a DATE off midnight refused, nothing past 64 bits of
//! nanoseconds) are [`TimeUnit`]'s.

use super::TimeUnit;
use crate::types::ElementaryType;
use crate::value::{TypeError, Value, MS_PER_DAY};

/// Nanoseconds in a millisecond.
pub(super) const NS_PER_MS: u64 = 1_000_000;

/// A value as read (DATE, TIME_OF_DAY and DATE_AND_TIME in `unit`) to the milliseconds
/// [`Value`] holds: see [`TimeUnit`] for why a sub-millisecond time is truncated and a
/// DATE off midnight refused.
pub(super) fn from_wire_unit(value: Value, unit: TimeUnit) -> Result<Value, TypeError> {
    if unit == TimeUnit::Milliseconds {
        return Ok(value);
    }
    let out_of_range = |ty: ElementaryType, ns: u64, why: &str| TypeError::OutOfRange {
        ty,
        value: format!("{ns} ns ({why})"),
    };
    Ok(match value {
        Value::Date(ns) if ns % (MS_PER_DAY * NS_PER_MS) != 0 => {
            return Err(out_of_range(ElementaryType::Date, ns, "not midnight"))
        }
        // Reported in the unit it came in, rather than as its truncated milliseconds.
        Value::TimeOfDay(ns) if ns / NS_PER_MS >= MS_PER_DAY => {
            return Err(out_of_range(
                ElementaryType::TimeOfDay,
                ns,
                "a day or more after midnight",
            ))
        }
        Value::Date(ns) => Value::Date(ns / NS_PER_MS),
        Value::TimeOfDay(ns) => Value::TimeOfDay(ns / NS_PER_MS),
        Value::DateAndTime(ns) => Value::DateAndTime(ns / NS_PER_MS),
        Value::Array(ty, items) => Value::Array(
            ty,
            items
                .into_iter()
                .enumerate()
                .map(|(index, item)| {
                    from_wire_unit(item, unit).map_err(|error| TypeError::Element {
                        index,
                        error: Box::new(error),
                    })
                })
                .collect::<Result<_, _>>()?,
        ),
        other => other,
    })
}

/// A DATE, TIME_OF_DAY or DATE_AND_TIME of `ms` milliseconds in `unit`; a value whose
/// nanoseconds do not fit 64 bits is refused (see [`TimeUnit`]).
pub(super) fn to_wire_unit(value: &Value, ms: u64, unit: TimeUnit) -> Result<u64, TypeError> {
    match unit {
        TimeUnit::Milliseconds => Ok(ms),
        TimeUnit::Nanoseconds => ms.checked_mul(NS_PER_MS).ok_or_else(|| {
            let shown = match crate::codec::json::value_to_json(value) {
                serde_json::Value::String(literal) => literal,
                other => other.to_string(),
            };
            TypeError::OutOfRange {
                ty: value.elementary_type(),
                value: format!(
                    "{shown} (fbdk's 64-bit nanoseconds end at DT#2554-07-21-23:34:33.709)"
                ),
            }
        }),
    }
}
