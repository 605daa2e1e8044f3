//! Reading the records: all of them, the local ones, or a page in id order (a range walk
//! under the lock, O(page)).

use std::sync::PoisonError;

use super::records::Record;
use super::Registry;

impl Registry {
    /// Every device, by id.
    pub fn list(&self) -> Vec<Record> {
        self.devices
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .values()
            .cloned()
            .collect()
    }

    /// One page of the devices `which` selects, in id order: the first `limit` with an id
    /// after `after`, and whether more follow. A range walk of the ordered records: only
    /// the page's records (and those `which` skips) are visited and copied under the lock,
    /// whatever the registry's size; the admin API's listing must not hold what sessions
    /// need while it serializes.
    pub fn page(
        &self,
        after: Option<&str>,
        limit: usize,
        which: impl Fn(&Record) -> bool,
    ) -> (Vec<Record>, bool) {
        use std::ops::Bound::{Excluded, Unbounded};
        let devices = self.devices.lock().unwrap_or_else(PoisonError::into_inner);
        let from = after.map_or(Unbounded, Excluded);
        let mut matching = devices
            .range::<str, _>((from, Unbounded))
            .map(|(_, record)| record)
            .filter(|record| which(record));
        let page: Vec<Record> = matching.by_ref().take(limit).cloned().collect();
        let more = matching.next().is_some();
        (page, more)
    }

    /// The local devices' records.
    pub fn local(&self) -> Vec<Record> {
        self.list()
            .into_iter()
            .filter(|r| r.line == self.line)
            .collect()
    }
}
