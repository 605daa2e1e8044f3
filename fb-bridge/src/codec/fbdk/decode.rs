//! Reading an `fbdk` payload: a cursor over its bytes ([`Reader`]) and one function per
//! kind of value, each checking the tag it expects and reporting truncation with where
//! the unfinished field starts.

use super::time::from_wire_unit;
use super::TimeUnit;
use super::{tag_of, ARRAY_TAG, EMPTY, FALSE_TAG, TRUE_TAG};
use crate::codec::CodecError;
use crate::types::{DataType, ElementaryType};
use crate::value::{TypeError, Value};

/// Decodes one value per (name, type) port, then requires the payload to be used up.
pub(super) fn decode_ports<N: AsRef<str>>(
    bytes: &[u8],
    ports: &[(N, DataType)],
    unit: TimeUnit,
) -> Result<Vec<Value>, CodecError> {
    if ports.is_empty() {
        return decode_empty(bytes).map(|()| Vec::new());
    }
    let mut reader = Reader::new(bytes, unit);
    let values = ports
        .iter()
        .map(|(name, ty)| read_port(&mut reader, name.as_ref(), *ty))
        .collect::<Result<Vec<_>, _>>()?;
    reader.finish()?;
    Ok(values)
}

/// A message without values is `0x05`; an empty payload is accepted too, since it says
/// the same and some publishers send it.
pub(super) fn decode_empty(bytes: &[u8]) -> Result<(), CodecError> {
    match bytes {
        [] | [EMPTY] => Ok(()),
        [EMPTY, rest @ ..] => Err(CodecError::Trailing(rest.len())),
        other => Err(CodecError::Trailing(other.len())),
    }
}

/// Reads the value of port `name`, brings its times from the wire unit to milliseconds,
/// and checks it against the port's type: the bytes fix the representation, not the
/// ranges (NaN, a TIME_OF_DAY past midnight, ...).
pub(super) fn read_port(
    reader: &mut Reader<'_>,
    name: &str,
    ty: DataType,
) -> Result<Value, CodecError> {
    let type_error = |error| CodecError::Type {
        port: name.to_owned(),
        error,
    };
    let value = match ty {
        DataType::Elementary(t) => read_scalar(reader, t)?,
        DataType::Array(t, n) => read_array(reader, t, n).map_err(|e| match e {
            ArrayError::Codec(e) => e,
            ArrayError::Length(e) => type_error(e),
        })?,
    };
    let value = from_wire_unit(value, reader.unit).map_err(type_error)?;
    value.check(ty).map_err(type_error)?;
    Ok(value)
}

/// Reads a tagged scalar. A BOOL's tag is its whole encoding, so it is read as a body.
pub(super) fn read_scalar(
    reader: &mut Reader<'_>,
    ty: ElementaryType,
) -> Result<Value, CodecError> {
    if ty != ElementaryType::Bool {
        reader.expect_tag(tag_of(ty), ty.name())?;
    }
    read_body(reader, ty)
}

/// Why an array could not be read: a wire problem, or a count other than the declared one
/// (a type error, which the caller names after the port).
pub(super) enum ArrayError {
    Codec(CodecError),
    Length(TypeError),
}

impl From<CodecError> for ArrayError {
    fn from(e: CodecError) -> Self {
        ArrayError::Codec(e)
    }
}

/// Reads `ARRAY [n] OF ty`: the array tag, the count, then the elements, which share one
/// tag unless they are BOOLs.
///
/// The count is compared with the declaration before anything is allocated, and the
/// vector's capacity is bounded by the bytes left, so a forged count cannot make the
/// decoder reserve memory the payload does not back.
pub(super) fn read_array(
    reader: &mut Reader<'_>,
    ty: ElementaryType,
    n: u16,
) -> Result<Value, ArrayError> {
    reader.expect_tag(ARRAY_TAG, &DataType::Array(ty, n).to_string())?;
    let count = usize::from(u16::from_be_bytes(reader.take_array()?));
    if count != usize::from(n) {
        return Err(ArrayError::Length(TypeError::ArrayLength {
            expected: usize::from(n),
            got: count,
        }));
    }
    if ty != ElementaryType::Bool {
        reader.expect_tag(tag_of(ty), ty.name())?;
    }
    let mut items = Vec::with_capacity(array_capacity(count, reader.remaining()));
    for _ in 0..count {
        items.push(read_body(reader, ty)?);
    }
    Ok(Value::Array(ty, items))
}

/// Capacity to reserve for `count` elements with `remaining` bytes left: every element
/// takes at least one byte, so no more than `remaining` of them can be there.
pub(super) fn array_capacity(count: usize, remaining: usize) -> usize {
    count.min(remaining)
}

/// Reads the bytes after a tag: the value of a `ty` in its fixed width or with its length.
/// A BOOL has no bytes after its tag, so its "body" is the tag byte itself; this is also
/// how each element of a BOOL array is written.
pub(super) fn read_body(reader: &mut Reader<'_>, ty: ElementaryType) -> Result<Value, CodecError> {
    use ElementaryType as T;
    Ok(match ty {
        T::Bool => Value::Bool(read_bool(reader)?),
        T::Sint => Value::Sint(i8::from_be_bytes(reader.take_array()?)),
        T::Int => Value::Int(i16::from_be_bytes(reader.take_array()?)),
        T::Dint => Value::Dint(i32::from_be_bytes(reader.take_array()?)),
        T::Lint => Value::Lint(i64::from_be_bytes(reader.take_array()?)),
        T::Usint => Value::Usint(u8::from_be_bytes(reader.take_array()?)),
        T::Uint => Value::Uint(u16::from_be_bytes(reader.take_array()?)),
        T::Udint => Value::Udint(u32::from_be_bytes(reader.take_array()?)),
        T::Ulint => Value::Ulint(u64::from_be_bytes(reader.take_array()?)),
        T::Real => Value::Real(f32::from_be_bytes(reader.take_array()?)),
        T::Lreal => Value::Lreal(f64::from_be_bytes(reader.take_array()?)),
        T::Byte => Value::Byte(u8::from_be_bytes(reader.take_array()?)),
        T::Word => Value::Word(u16::from_be_bytes(reader.take_array()?)),
        T::Dword => Value::Dword(u32::from_be_bytes(reader.take_array()?)),
        T::Lword => Value::Lword(u64::from_be_bytes(reader.take_array()?)),
        T::Time => Value::Time(i64::from_be_bytes(reader.take_array()?)),
        T::Date => Value::Date(u64::from_be_bytes(reader.take_array()?)),
        T::TimeOfDay => Value::TimeOfDay(u64::from_be_bytes(reader.take_array()?)),
        T::DateAndTime => Value::DateAndTime(u64::from_be_bytes(reader.take_array()?)),
        T::String => Value::String(read_string(reader)?),
        T::WString => Value::WString(read_wstring(reader)?),
    })
}

/// A BOOL: `0x41` TRUE, `0x40` FALSE; any other byte is a wrong tag.
pub(super) fn read_bool(reader: &mut Reader<'_>) -> Result<bool, CodecError> {
    let offset = reader.pos;
    match reader.take_array::<1>()? {
        [TRUE_TAG] => Ok(true),
        [FALSE_TAG] => Ok(false),
        [tag] => Err(tag_error(offset, tag, ElementaryType::Bool.name())),
    }
}

/// A STRING: UTF-8 when the bytes are UTF-8, Latin-1 otherwise (see the module doc).
pub(super) fn read_string(reader: &mut Reader<'_>) -> Result<String, CodecError> {
    let len = usize::from(u16::from_be_bytes(reader.take_array()?));
    let bytes = reader.take(len)?;
    Ok(match std::str::from_utf8(bytes) {
        Ok(text) => text.to_owned(),
        Err(_) => bytes.iter().map(|&b| char::from(b)).collect(),
    })
}

/// A WSTRING: big-endian UTF-16 units; an unpaired surrogate is malformed.
pub(super) fn read_wstring(reader: &mut Reader<'_>) -> Result<String, CodecError> {
    let units = usize::from(u16::from_be_bytes(reader.take_array()?));
    let offset = reader.pos;
    let bytes = reader.take(units * 2)?;
    let units = bytes
        .chunks_exact(2)
        .map(|pair| u16::from_be_bytes([pair[0], pair[1]]));
    char::decode_utf16(units)
        .collect::<Result<String, _>>()
        .map_err(|e| {
            CodecError::Malformed(format!(
                "WSTRING at offset {offset}: unpaired UTF-16 surrogate 0x{:04x}",
                e.unpaired_surrogate()
            ))
        })
}

pub(super) fn tag_error(offset: usize, tag: u8, expected: &str) -> CodecError {
    CodecError::Tag {
        offset,
        tag,
        expected: expected.to_owned(),
    }
}

/// A cursor over the payload whose every read is bounds-checked: running out of bytes is
/// a [`CodecError::Truncated`], never a panic.
pub(super) struct Reader<'a> {
    bytes: &'a [u8],
    /// Offset of the next unread byte; never beyond `bytes.len()`.
    pos: usize,
    /// The unit DATE, TIME_OF_DAY and DATE_AND_TIME are read in.
    unit: TimeUnit,
}

impl<'a> Reader<'a> {
    pub(super) fn new(bytes: &'a [u8], unit: TimeUnit) -> Self {
        Reader {
            bytes,
            pos: 0,
            unit,
        }
    }

    pub(super) fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// The next `n` bytes, or how many are missing.
    pub(super) fn take(&mut self, n: usize) -> Result<&'a [u8], CodecError> {
        let rest = self.bytes.get(self.pos..).unwrap_or_default();
        match rest.get(..n) {
            Some(taken) => {
                self.pos += n;
                Ok(taken)
            }
            None => Err(CodecError::Truncated {
                offset: self.pos,
                needed: n - rest.len(),
            }),
        }
    }

    /// The next `N` bytes as an array, for `from_be_bytes`.
    pub(super) fn take_array<const N: usize>(&mut self) -> Result<[u8; N], CodecError> {
        let mut out = [0; N];
        // `take` returns exactly N bytes or an error, so the lengths match.
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    /// Reads a tag byte that must be `tag`; `expected` names the type in the error.
    pub(super) fn expect_tag(&mut self, tag: u8, expected: &str) -> Result<(), CodecError> {
        let offset = self.pos;
        match self.take_array::<1>()? {
            [found] if found == tag => Ok(()),
            [found] => Err(tag_error(offset, found, expected)),
        }
    }

    /// Every byte must have been read.
    pub(super) fn finish(self) -> Result<(), CodecError> {
        match self.remaining() {
            0 => Ok(()),
            n => Err(CodecError::Trailing(n)),
        }
    }
}
