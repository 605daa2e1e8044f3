//! Types of data ports: a `PUBLISH_n`'s SD and a `SUBSCRIBE_n`'s RD ports are ANY, so
//! their type is read off what the boot file says about the pins they are wired to (the
//! type table's port types, and every typed literal written to a pin), one function per
//! direction. The module `fboot` lists the order in which each source counts.

use super::comm::base_type;
use super::resource::{PortRef, Resource};
use super::TypeTable;
use crate::types::{DataType, ElementaryType};

/// The type of a parameter's literal, or why it has none.
pub(super) fn literal_type(literal: &str) -> Result<DataType, String> {
    let text = literal.trim();
    let untyped = || {
        format!(
            "it is given the untyped value {text:?}, which FORTE 2.0.x even refuses on an \
             ANY input; a typed literal such as INT#3 or REAL#1.5 says its type"
        )
    };
    if text.starts_with('[') {
        return Err(format!(
            "it is given the array {text:?}, whose element type and length the literal does \
             not fix"
        ));
    }
    if text.eq_ignore_ascii_case("TRUE") || text.eq_ignore_ascii_case("FALSE") {
        return Ok(DataType::Elementary(ElementaryType::Bool));
    }
    if text.starts_with('\'') {
        return Ok(DataType::Elementary(ElementaryType::String));
    }
    if text.starts_with('"') {
        return Ok(DataType::Elementary(ElementaryType::WString));
    }
    let Some((prefix, _)) = text.split_once('#') else {
        return Err(untyped());
    };
    let upper = prefix.trim().to_ascii_uppercase();
    let name = match upper.as_str() {
        "T" => "TIME",
        "D" => "DATE",
        base if base.bytes().all(|b| b.is_ascii_digit()) => return Err(untyped()),
        other => other,
    };
    name.parse::<ElementaryType>()
        .map(DataType::Elementary)
        .map_err(|_| {
            format!("it is given {text:?}, a {prefix} literal, a type fbbus does not carry")
        })
}

/// The type of pin `fb.port` of `resource`: its FB type's port type from the type table,
/// else the typed literal written to it (a parameter, or an output's initial value).
pub(super) fn pin_type(
    resource: &Resource,
    (fb, port): &PortRef,
    types: &TypeTable,
) -> Result<DataType, String> {
    let fb_type = resource.fb_type(fb).ok_or_else(|| {
        format!(
            "{fb}.{port}, and {fb} is not an FB of resource {}",
            resource.name
        )
    })?;
    let known = types
        .get(fb_type)
        .or_else(|| types.get(base_type(fb_type)))
        .and_then(|ports| ports.get(port));
    let Some(type_name) = known else {
        let literal = resource.param(fb, port).and_then(|l| literal_type(l).ok());
        return literal.ok_or_else(|| {
            format!(
                "{fb}.{port}, a port of {fb_type}, whose interface the boot file does not \
                 contain"
            )
        });
    };
    type_name
        .parse::<DataType>()
        .map_err(|_| format!("{fb}.{port}, of type {type_name}, which fbbus does not carry"))
}

/// A port's derived type, and the advisory note's text when the pins it joins were
/// declared with different types (the type kept is the one of the data's source).
#[derive(Debug)]
pub(super) struct Derived {
    pub(super) ty: DataType,
    pub(super) mismatch: Option<String>,
}

/// The type of a sending port (`SD_i` of a PUBLISH): that of the output wired into it,
/// else the typed literal written to it. The source of the data wins: a literal of
/// another type on the port itself is named in the mismatch.
pub(super) fn sending_type(
    resource: &Resource,
    instance: &str,
    port: &str,
    types: &TypeTable,
) -> Result<Derived, String> {
    let own = resource.param(instance, port);
    let Some(source) = resource.sources_of(instance, port).first() else {
        return match own {
            Some(literal) => literal_type(literal).map(|ty| Derived { ty, mismatch: None }),
            None => Err("it is neither connected nor given a value".into()),
        };
    };
    let from_source =
        pin_type(resource, source, types).map_err(|why| format!("it is fed by {why}"));
    let own_type = own.and_then(|literal| literal_type(literal).ok());
    match (from_source, own_type) {
        (Ok(ty), Some(other)) if other != ty => Ok(Derived {
            ty,
            mismatch: Some(format!(
                "{instance}.{port} is fed a {ty} by {}.{} but is given the {other} value {:?}",
                source.0,
                source.1,
                own.unwrap_or_default().trim()
            )),
        }),
        (Ok(ty), _) => Ok(Derived { ty, mismatch: None }),
        (Err(_), Some(ty)) => Ok(Derived { ty, mismatch: None }),
        (Err(why), None) => Err(why),
    }
}

/// The type of a receiving port (`RD_i` of a SUBSCRIBE): the typed literal written to it
/// (its declared type, the source of what it feeds) if any, else that of the inputs it
/// feeds when those known agree. An input of another type than the literal's is named in
/// the mismatch.
pub(super) fn receiving_type(
    resource: &Resource,
    instance: &str,
    port: &str,
    types: &TypeTable,
) -> Result<Derived, String> {
    let mut known: Vec<(&PortRef, DataType)> = Vec::new();
    let mut unknown = Vec::new();
    for destination in resource.destinations_of(instance, port) {
        match pin_type(resource, destination, types) {
            Ok(t) => known.push((destination, t)),
            Err(why) => unknown.push(why),
        }
    }
    let listed = |pins: &[(&PortRef, DataType)]| {
        pins.iter()
            .map(|((fb, port), t)| format!("{fb}.{port} {t}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let own = resource.param(instance, port);
    if let Some(ty) = own.and_then(|literal| literal_type(literal).ok()) {
        let other: Vec<(&PortRef, DataType)> =
            known.into_iter().filter(|(_, t)| *t != ty).collect();
        let mismatch = (!other.is_empty()).then(|| {
            format!(
                "{instance}.{port} is given the {ty} value {:?} but feeds {}",
                own.unwrap_or_default().trim(),
                listed(&other)
            )
        });
        return Ok(Derived { ty, mismatch });
    }
    match known.first() {
        Some((_, first)) if known.iter().all(|(_, t)| t == first) => Ok(Derived {
            ty: *first,
            mismatch: None,
        }),
        Some(_) => Err(format!(
            "it feeds ports of different types ({})",
            listed(&known)
        )),
        None if unknown.is_empty() => Err("it is connected to nothing".into()),
        None => Err(format!("it feeds only {}", unknown.join("; and "))),
    }
}
