//! Device profiles derived from a 4diac FORTE boot file (`.fboot`).
//!
//! A FORTE device's MQTT traffic is written down nowhere but in its application: the
//! `PUBLISH_n` and `SUBSCRIBE_n` FBs, their `ID` parameters (`fbdk[].mqtt[broker, client
//! id, topic]`) and what is wired to their data ports. 4diac IDE deploys that application
//! as management commands, and the boot file is those commands saved, the form in which a
//! FORTE device starts by itself. [`import`] reads one and writes the profiles
//! ([`ProfileFile`]) that say for the device what it cannot declare, with a note for
//! everything the file does not tell.
//!
//! DINASORE keeps what 4diac IDE deploys to it in the same syntax
//! (`resources/data_model.fboot`), but reads it otherwise, has MQTT FBs of its own and no
//! client ids: [`import_dinasore`] derives its profile from that file (its module,
//! `fboot/dinasore.rs`, says how), with the parsing below.
//!
//! # The boot file
//!
//! One command per line, `<resource>;<request>`: the resource the request goes to (empty
//! for the device itself), a `;`, then one management request in XML:
//!
//! ```text
//! ;<Request ID="1" Action="CREATE"><FB Name="EMB_RES" Type="EMB_RES" /></Request>
//! EMB_RES;<Request ID="2" Action="CREATE"><FB Name="PUB_POS" Type="PUBLISH_1" /></Request>
//! EMB_RES;<Request ID="3" Action="WRITE"><Connection Source="fbdk[].mqtt[tcp://10.0.0.5:1883, conv1, line1/conv1/position]" Destination="PUB_POS.ID" /></Request>
//! EMB_RES;<Request ID="4" Action="CREATE"><Connection Source="POS2REAL.OUT" Destination="PUB_POS.SD_1" /></Request>
//! EMB_RES;<Request ID="5" Action="START"/>
//! ```
//!
//! `CREATE` with an `FB` makes an FB instance, with a `Connection` a connection between two
//! ports; `WRITE` with a `Connection` sets a parameter (its `Source` is the value, XML
//! escaped); `DELETE` undoes a `CREATE`; the rest (`START`, ...) changes nothing here. The
//! file is read the way FORTE reads it, and where FORTE is strict the importer is too, so
//! a profile describes the application the device really runs:
//!
//! - a command may continue over several lines, up to a line that ends in `</Request>` or
//!   `/>`; the first `;` ends the resource name;
//! - FORTE stops loading at the first command it cannot execute, so at a line without `;`
//!   or a request it cannot parse the import stops too, with a note; nothing after it
//!   exists on the device;
//! - a parameter's XML escapes are the five FORTE decodes (`&quot;`, `&apos;`, `&amp;`,
//!   `&lt;`, `&gt;`); any other `&` stays as it is, as it does in FORTE;
//! - the `ID` is a STRING or WSTRING value: a `WSTRING#`/`STRING#` prefix is dropped, a
//!   quoted literal (`"..."`, `'...'`) is unquoted with its `$` escapes; its layers are
//!   split at unescaped `[` and `]` (`\` escapes them), and the `mqtt[]` layer takes
//!   exactly three comma-separated parameters with the spaces around them trimmed;
//! - lines ending in CRLF are read as lines, with a note: FORTE finds the end of a command
//!   only before a bare LF (but on Windows, where reading the file as text drops the CR).
//!
//! # One profile per MQTT client id
//!
//! The broker recognises a device by its connection, and every MQTT FB of a FORTE device
//! names the connection it uses by client id, so the FBs are grouped by client id and each
//! group is one profile: `device` is the client id when it is a usable device id (else a
//! sanitized one, with a note), `identity.client_id` is the client id as FORTE sends it.
//! FORTE 2.0.x keeps one MQTT client per runtime and 3.x one per broker address, so a file
//! with more client ids than that gets a note saying which FBs fail to initialise.
//!
//! How the device speaks is what FORTE's MQTT layer does: `fbdk` payloads (the `fbdk[]`
//! layer), a largest receivable message of 255 bytes (`MQTTComLayer`'s receive buffer: a
//! longer message is cut there), QoS 0 (the layer publishes and subscribes at QoS 0), and
//! DATE/TIME_OF_DAY/DATE_AND_TIME in nanoseconds, FORTE 3.x's unit: the boot file does
//! not say the version, so a profile with such a port gets a note to set `ms` for 2.0.x.
//!
//! # PUBLISH is an output, SUBSCRIBE an input
//!
//! A profile describes the device as the bus sees it, and what a `PUBLISH_n` FB sends is
//! what the device publishes, so the FB becomes an **output** of the profile, whatever
//! its ports are called inside the device. An instance `X` of `PUBLISH_n` becomes the FB
//! `X` with
//!
//! ```text
//! events_out: { REQ: { with: [SD_1, ..., SD_n] } }
//! data_out:   { SD_1: <type of SD_1>, ..., SD_n: <type of SD_n> }
//! ```
//!
//! and its topic maps onto `X.REQ`. The names stay the ones the engineer sees on the FB
//! in 4diac IDE: the message on the topic is what `X` sends at `REQ`. The topic maps onto
//! the event, not onto a data port, because FORTE sends SD_1..SD_n of one `REQ` together
//! as one `fbdk` message, which is exactly an event with that WITH list in that order (a
//! `PUBLISH_0` sends an event without data, `0x05`). An instance `Y` of `SUBSCRIBE_n` is
//! the same the other way round, an **input**: the FB `Y` with `events_in: { IND: { with:
//! [RD_1, ...] } }` and `data_in: { RD_1: ..., ... }`, its topic mapped onto `Y.IND`.
//!
//! An input topic needs `from`, the typed output that feeds it, and which device feeds a
//! topic is not in one device's boot file: it is left out, so the profile does not pass
//! [`ProfileFile::validate`] until it is set, and a blocking note says so. When a PUBLISH of the
//! same import publishes that topic, it is not mapped at all: FORTE reaches FORTE on
//! that topic through the broker as it always did, and a topic that is one device's
//! output cannot also be another's input.
//!
//! A topic already in a typed namespace (`fbdk/<device>/<FB>/<PORT>`) is not mapped: the
//! broker types it already. A SUBSCRIBE reading one needs nothing; a PUBLISH writing one
//! in its own device's namespace needs its port in the interface, so the FB `<FB>` gets
//! `<PORT>`: the data port itself for a `PUBLISH_1` (its message is that one value), an
//! event with WITH `SD_1..SD_n` otherwise.
//!
//! # Data types
//!
//! A `PUBLISH_n`'s SD ports and a `SUBSCRIBE_n`'s RD ports are of type ANY: their type is
//! the type of what is wired to them, and that type belongs to the FB type at the other
//! end, whose interface the boot file does not contain. It is derived (module `typing`)
//! from what the file says about each pin the port is wired to:
//!
//! 1. the pin's port type when the type table knows its FB type. [`import`] uses
//!    [`builtin_types`]: the IEC 61131-3 conversions (`F_INT_TO_REAL`: `IN` INT, `OUT`
//!    REAL), FORTE's `INT2INT`-style data FBs, its event FBs with data (`E_CTU`,
//!    `E_SWITCH`, `E_CYCLE`, ...), the IEC 61131-3 FBs (`FB_TON`, `FB_CTU`, ...) and the
//!    process-image FBs (`IX`, `QW`, ...), each read from FORTE's own type.
//!    [`import_with_types`] takes another table, for a caller who has the application's
//!    own `.fbt` files;
//! 2. else a typed literal written to that pin (`DT#...`, `INT#3`, `T#1s`, `'text'`,
//!    `TRUE`); an untyped one (`3`, `1.5`) gives nothing (and FORTE 2.0.x refuses it: an
//!    ANY input takes only `<TYPE>#<value>`).
//!
//! A literal written to the port itself counts too: `X.SD_i` takes the type of the
//! output wired into it, else its own literal; `Y.RD_i` takes its own literal (it is the
//! source of what it feeds), else the type of the inputs it feeds when all that are
//! known agree. Where the two sides disagree (a DINT into an INT), the type of the data's
//! source is kept and an advisory note names both; so too between a PUBLISH and a
//! SUBSCRIBE of the import on one topic, where the publisher's type wins.
//!
//! Otherwise the port is left out of the profile, with a note. It stays in its event's
//! WITH list, so [`ProfileFile::validate`] refuses the profile ("WITH SD_2: no data
//! output of that name") until its type is written in: a profile that loads must decode
//! the device's messages right, and one with a WITH value missing would misread every
//! message (there is no `ANY` to put instead; the `fbdk` codec needs each value's type).
//!
//! # Notes, and names
//!
//! Every [`Note`] says whether it blocks: a blocking note is one validation error of the
//! profile it names (an untyped port, an input topic without `from`), so a caller can say
//! how many edits stand between the printed profile and `fbbus declare`, and list those
//! first. [`import_named`] (and [`import_dinasore_named`]) names the generated ports as
//! the user asks ([`PortNames`]: `P_COUNT.SD_1` → `COUNT`), while the FB is built, so the
//! interface, WITH lists, topic mappings and notes agree.
//!
//! # Not imported
//!
//! Each with a note naming the FB and what to do: a `raw[]` layer (its payload is the
//! bytes of one STRING, with no type to check), `CLIENT_n_m`/`SERVER_n_m` FBs (fbbus has
//! no request/response mapping, and FORTE's MQTT layer does not implement them either),
//! FBs that do not use MQTT, an `ID` that is not a parameter or is malformed, wildcard
//! subscriptions, topics in the broker's own `fbbus/` namespace, and topics mapped twice.
//!
//! # Untrusted input
//!
//! A boot file comes from outside: the importer never panics, whatever the text (no
//! indexing; text is only split at the characters it looks for, and cut at character
//! boundaries), and every lookup goes through an ordered map, so a hostile file costs
//! time in proportion to its size, not to its square.
//!
//! # FORTE sources read
//!
//! eclipse-4diac/4diac-forte (snapshot b70b4b7f, December 2021, 2.0.x merged), for the
//! format and its reading: `src/stdfblib/ita/ForteBootFileLoader.cpp` (lines, `;`,
//! command ends, stopping), `src/stdfblib/ita/DEV_MGR.cpp` (the requests),
//! `src/core/utils/string_utils.{h,cpp}` (XML escapes, `\` escapes),
//! `src/core/cominfra/basecommfb.cpp` (layers of an ID, the default `fbdk[].ip[]`),
//! `src/core/cominfra/commfb.cpp` (`PUBLISH_n`/`SUBSCRIBE_n` ports, WSTRING `ID`),
//! `src/core/datatypes/forte_wstring.cpp`, `forte_string.cpp`, `forte_any_string.cpp`
//! (the literal of an ID), `forte_any.cpp` (`fromString` of an ANY input), `src/core/utils/parameterParser.cpp` (the three parameters),
//! `src/com/mqtt_paho/MQTTComLayer.{h,cpp}` (255-byte buffer, QoS 0, client/server not
//! implemented), `src/com/mqtt_paho/MQTTHandler.cpp` (2.0.x: one client per runtime; the
//! 3.x version, one client per broker address, from its 2023 source), and the port types
//! of the FBs in [`builtin_types`] from their sources under `src/modules/IEC61131-3`,
//! `src/modules/convert`, `src/stdfblib/events`, `src/stdfblib/io` and
//! `src/stdfblib/timedfb.cpp`.
//!
//! # Modules
//!
//! One concept each: `load` (the file's commands, as FORTE runs them) over `xml` (a
//! request's tags) into a `resource` (the application they build); `comm` (which FBs
//! communicate, and their `ID`s); `typing` (port types from the type table and the
//! literals); `draft` (the profile being built, and the one function per direction that
//! both importers use to put an MQTT FB into it); `forte` (FORTE's grouping by client id);
//! `dinasore` (DINASORE's reading); `builtin` (the built-in type table); `note` and
//! `names` (what an import says, and the port names a user chooses).

use std::collections::BTreeMap;

mod builtin;
mod comm;
mod dinasore;
mod draft;
mod forte;
mod load;
mod names;
mod note;
mod resource;
mod typing;
mod xml;

pub use builtin::builtin_types;
pub use dinasore::{import_dinasore, import_dinasore_named};
pub use names::{NameError, PortNames};
pub use note::Note;

use super::ProfileFile;
use note::Notes;

#[cfg(test)]
use {
    crate::codec::Encoding,
    crate::interface::is_identifier,
    crate::topic,
    crate::types::{DataType, ElementaryType},
    comm::{layers, string_value},
    draft::{sanitized_device, sanitized_identifier, unique},
    typing::literal_type,
    xml::decode_entities,
};

/// FB type name → port name → IEC 61131-3 type name, as in the FB type's interface.
pub type TypeTable = BTreeMap<String, BTreeMap<String, String>>;

/// The largest message FORTE's MQTT layer receives: its buffer (`MQTTComLayer`,
/// `mBufferSize`) cuts longer ones.
pub const FORTE_MAX_PAYLOAD: usize = 255;

/// What a boot file gives: one profile per MQTT client id ([`import`]; one for the file with
/// [`import_dinasore`]), and a note for each thing it could not derive or the user should
/// check, naming the FB and what to do, in the order the file is read.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FbootImport {
    pub profiles: Vec<ProfileFile>,
    pub notes: Vec<Note>,
}

impl FbootImport {
    /// How many notes block a profile: each is one reason `fbbus declare` refuses it.
    pub fn blocking(&self) -> usize {
        self.notes.iter().filter(|n| n.is_blocking()).count()
    }

    /// The notes, those that block a profile first, each group in the order written.
    pub fn notes_blocking_first(&self) -> Vec<&Note> {
        let (mut blocking, advisory): (Vec<&Note>, Vec<&Note>) =
            self.notes.iter().partition(|n| n.is_blocking());
        blocking.extend(advisory);
        blocking
    }
}

/// Derives profiles from a boot file's text, with FB port types from [`builtin_types`].
pub fn import(text: &str) -> FbootImport {
    import_with_types(text, &builtin_types())
}

/// Derives profiles from a boot file's text, with FB port types from `types` (only: merge
/// [`builtin_types`] in to keep them).
pub fn import_with_types(text: &str, types: &TypeTable) -> FbootImport {
    import_named(text, types, &mut PortNames::new())
}

/// [`import_with_types`], with the generated ports named as `names` says; what is wrong
/// with the names is in [`PortNames::finish`] afterwards.
pub fn import_named(text: &str, types: &TypeTable, names: &mut PortNames) -> FbootImport {
    let mut notes = Notes::default();
    let resources = load::load(text, &mut notes);
    let comm = comm::find_comm_fbs(&resources, &mut notes);
    let profiles = forte::build_profiles(&comm, types, &mut notes, names);
    FbootImport {
        profiles,
        notes: notes.into_vec(),
    }
}

#[cfg(test)]
mod tests;
