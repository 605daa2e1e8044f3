//! The notes of an import: a sentence for each thing the boot file does not tell or the
//! user should check, naming the FB and what to do, and whether it **blocks**: a blocking
//! note is one of the reasons `fbbus declare` (and [`ProfileFile::validate`]) refuses the
//! profile as printed, so a user can tell the edits that must be made from the advice.
//!
//! Each blocking note stands for exactly one validation error of its profile (an untyped
//! port left in a WITH list, an input topic without `from`), so the count a summary gives
//! and the count `fbbus profile check` gives agree.
//!
//! [`ProfileFile::validate`]: crate::profile::ProfileFile::validate

use std::fmt;
use std::ops::Deref;

/// One note of an import.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Note {
    pub text: String,
    /// The device whose profile is refused until this note is followed; None: advisory.
    pub blocks: Option<String>,
}

impl Note {
    /// Whether the profile it names is refused until this note is followed.
    pub fn is_blocking(&self) -> bool {
        self.blocks.is_some()
    }
}

/// An advisory note.
impl From<String> for Note {
    fn from(text: String) -> Note {
        Note { text, blocks: None }
    }
}

impl Deref for Note {
    type Target = str;
    fn deref(&self) -> &str {
        &self.text
    }
}

impl fmt::Display for Note {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

impl PartialEq<str> for Note {
    fn eq(&self, other: &str) -> bool {
        self.text == other
    }
}

impl PartialEq<&str> for Note {
    fn eq(&self, other: &&str) -> bool {
        self.text == *other
    }
}

impl PartialEq<String> for Note {
    fn eq(&self, other: &String) -> bool {
        &self.text == other
    }
}

/// The notes being written, in the order the file is read.
#[derive(Debug, Default)]
pub(super) struct Notes(Vec<Note>);

impl Notes {
    /// An advisory note.
    pub(super) fn push(&mut self, text: impl Into<String>) {
        self.0.push(Note {
            text: text.into(),
            blocks: None,
        });
    }

    /// How many notes there are: the index the next one gets.
    pub(super) fn len(&self) -> usize {
        self.0.len()
    }

    /// A note that blocks the profile of `device`; its index, for [`Notes::get_mut`].
    pub(super) fn blocking(&mut self, device: &str, text: impl Into<String>) -> usize {
        self.0.push(Note {
            text: text.into(),
            blocks: Some(device.to_owned()),
        });
        self.0.len() - 1
    }

    pub(super) fn get_mut(&mut self, index: usize) -> Option<&mut Note> {
        self.0.get_mut(index)
    }

    pub(super) fn into_vec(self) -> Vec<Note> {
        self.0
    }
}
