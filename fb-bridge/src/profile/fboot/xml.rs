//! The XML of one management request, read the way the runtime reads it: start tags with
//! their attributes (values decoded by the caller's rules, FORTE's five escapes or
//! expat's), end tags by name, text between them skipped. Hand-written rather than a
//! parser crate because each runtime accepts and refuses different things, and the
//! importer must refuse exactly what the runtime does.

/// An XML start tag: its name and attributes, values unescaped.
#[derive(Debug)]
pub(super) struct Tag {
    pub(super) name: String,
    pub(super) attrs: Vec<(String, String)>,
}

impl Tag {
    pub(super) fn attr(&self, key: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// The start tags of a request, in order, read the way FORTE reads them; end tags are
/// skipped.
pub(super) fn start_tags(text: &str) -> Result<Vec<Tag>, String> {
    Ok(xml_items(text, |value| Ok(decode_entities(value)))?
        .into_iter()
        .filter_map(|item| match item {
            XmlItem::Start { tag, .. } => Some(tag),
            XmlItem::End(_) => None,
        })
        .collect())
}

/// A tag of a request: a start tag (`empty` if it closes itself, `<FB ... />`) or an end
/// tag, with its name.
#[derive(Debug)]
pub(super) enum XmlItem {
    Start { tag: Tag, empty: bool },
    End(String),
}

/// The tags of a request, in order, attribute values decoded by `decode` (Err: why the
/// value is not one the reader takes); text between tags is skipped.
pub(super) fn xml_items(
    text: &str,
    decode: impl Fn(&str) -> Result<String, String>,
) -> Result<Vec<XmlItem>, String> {
    let mut items = Vec::new();
    let mut rest = text;
    while let Some((_, after)) = rest.split_once('<') {
        if let Some(end_tag) = after.strip_prefix('/') {
            let (name, after) = end_tag
                .split_once('>')
                .ok_or("an end tag is not closed with '>'")?;
            items.push(XmlItem::End(name.trim().to_owned()));
            rest = after;
            continue;
        }
        let (tag, empty, after) = start_tag(after, &decode)?;
        items.push(XmlItem::Start { tag, empty });
        rest = after;
    }
    Ok(items)
}

/// One start tag after its `<`, whether it closes itself, and the text after it.
pub(super) fn start_tag<'t>(
    text: &'t str,
    decode: &impl Fn(&str) -> Result<String, String>,
) -> Result<(Tag, bool, &'t str), String> {
    let name_end = text
        .find(|c: char| c.is_whitespace() || c == '/' || c == '>')
        .ok_or("a tag is not closed")?;
    let (name, mut rest) = text.split_at_checked(name_end).ok_or("a tag is cut")?;
    if name.is_empty() {
        return Err("a tag has no name".into());
    }
    let mut attrs = Vec::new();
    loop {
        rest = rest.trim_start();
        let closed = match rest.strip_prefix("/>") {
            Some(after) => Some((true, after)),
            None => rest.strip_prefix('>').map(|after| (false, after)),
        };
        if let Some((empty, after)) = closed {
            let tag = Tag {
                name: name.to_owned(),
                attrs,
            };
            return Ok((tag, empty, after));
        }
        let (key, after) = rest
            .split_once('=')
            .ok_or_else(|| format!("tag <{name}> is cut or has an attribute without a value"))?;
        let key = key.trim();
        if key.is_empty() || key.contains(|c: char| c.is_whitespace() || "<>/\"'".contains(c)) {
            return Err(format!("tag <{name}> has a malformed attribute"));
        }
        let after = after.trim_start();
        let quote = match after.chars().next() {
            Some(q @ ('"' | '\'')) => q,
            _ => return Err(format!("attribute {key} of <{name}> is not quoted")),
        };
        let (value, after) = after
            .strip_prefix(quote)
            .and_then(|v| v.split_once(quote))
            .ok_or_else(|| format!("attribute {key} of <{name}> has no closing quote"))?;
        let value = decode(value).map_err(|why| format!("attribute {key} of <{name}>: {why}"))?;
        attrs.push((key.to_owned(), value));
        rest = after;
    }
}

/// The five XML escapes FORTE decodes in a parameter; any other `&` is kept.
pub(super) fn decode_entities(text: &str) -> String {
    const ENTITIES: [(&str, char); 5] = [
        ("&quot;", '"'),
        ("&apos;", '\''),
        ("&amp;", '&'),
        ("&lt;", '<'),
        ("&gt;", '>'),
    ];
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some((before, after)) = rest.split_once('&') {
        out.push_str(before);
        let with_amp = rest.get(before.len()..).unwrap_or("");
        match ENTITIES.iter().find(|(e, _)| with_amp.starts_with(e)) {
            Some((entity, c)) => {
                out.push(*c);
                rest = with_amp.get(entity.len()..).unwrap_or("");
            }
            None => {
                out.push('&');
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}
