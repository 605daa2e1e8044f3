//! Messages lost on the bus, counted on both sides (issue 32).
//!
//! Only a receiving line can tell a message never reached it: [`super::Gaps`] sees the
//! hole in a topic's numbering. So each receiving line keeps, per origin line, how many of
//! that origin's messages it counted as lost ([`LossTally`]), and tells the origin: once a
//! second at most, and only when the count moved, it puts a [`LossReport`] on
//! `fbbus/@/loss/<receiver>/<origin>` (a key only the receiver may put on, on a
//! mutual-TLS bus). The origin adds up what each receiver reports ([`Reported`]) and so
//! counts, as the sender, what it put on the bus and was lost on the way.
//!
//! Reports are cumulative, not increments: a report lost, repeated, or delivered through
//! two routers changes nothing, and the next one carries the whole count. Each report
//! names the origin's epoch (a count about an earlier run of the origin is not its own)
//! and the receiver's (a receiver that restarted counts from 0 again).

use std::collections::HashMap;

/// Origin lines a [`LossTally`] counts for, and receiving lines a [`Reported`] follows.
/// A plant has tens of lines; one beyond this is not counted (and logged by the caller).
pub const LOSS_LINES: usize = 1024;

/// What a receiving line tells an origin: of the origin's run `origin_epoch`, how many
/// messages the receiver's run `receiver_epoch` counted as lost so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LossReport {
    pub origin_epoch: u64,
    pub receiver_epoch: u64,
    pub lost: u64,
}

impl LossReport {
    /// Three big-endian u64: origin epoch, receiver epoch, lost.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(24);
        out.extend_from_slice(&self.origin_epoch.to_be_bytes());
        out.extend_from_slice(&self.receiver_epoch.to_be_bytes());
        out.extend_from_slice(&self.lost.to_be_bytes());
        out
    }

    /// [`LossReport::encode`]'s inverse; `None` for anything else.
    pub fn decode(bytes: &[u8]) -> Option<LossReport> {
        if bytes.len() != 24 {
            return None;
        }
        let word = |i: usize| -> Option<u64> {
            Some(u64::from_be_bytes(
                bytes.get(i * 8..i * 8 + 8)?.try_into().ok()?,
            ))
        };
        Some(LossReport {
            origin_epoch: word(0)?,
            receiver_epoch: word(1)?,
            lost: word(2)?,
        })
    }
}

/// The receiving side: per origin line, the messages of its current run counted lost.
#[derive(Debug, Default)]
pub struct LossTally {
    origins: HashMap<String, Tally>,
}

#[derive(Debug, Default)]
struct Tally {
    epoch: u64,
    lost: u64,
    /// Not reported since it last moved.
    changed: bool,
}

impl LossTally {
    /// `lost` messages of `origin`'s run `epoch` never arrived. False if `origin` is
    /// one line more than [`LOSS_LINES`]: not counted.
    pub fn add(&mut self, origin: &str, epoch: u64, lost: u64) -> bool {
        if !self.origins.contains_key(origin) {
            if self.origins.len() >= LOSS_LINES {
                return false;
            }
            self.origins.insert(origin.to_owned(), Tally::default());
        }
        let Some(t) = self.origins.get_mut(origin) else {
            return false;
        };
        if epoch != t.epoch {
            if epoch < t.epoch {
                // A message of an earlier run still in flight: that run's count is gone.
                return true;
            }
            *t = Tally {
                epoch,
                ..Tally::default()
            };
        }
        t.lost = t.lost.saturating_add(lost);
        t.changed = true;
        true
    }

    /// The reports to put, as (origin, report), for a receiver whose run is
    /// `receiver_epoch`: of the counts that moved since the last call, or of every count
    /// (`everything`: sent again now and then, in case a report was lost with a router).
    pub fn reports(&mut self, receiver_epoch: u64, everything: bool) -> Vec<(String, LossReport)> {
        self.origins
            .iter_mut()
            .filter(|(_, t)| t.changed || everything)
            .map(|(origin, t)| {
                t.changed = false;
                let report = LossReport {
                    origin_epoch: t.epoch,
                    receiver_epoch,
                    lost: t.lost,
                };
                (origin.clone(), report)
            })
            .collect()
    }
}

/// The sending side: per receiving line, the last count it reported of this line's run.
#[derive(Debug)]
pub struct Reported {
    own_epoch: u64,
    receivers: HashMap<String, (u64, u64)>,
}

impl Reported {
    /// For the origin whose run is `own_epoch`.
    pub fn new(own_epoch: u64) -> Self {
        Reported {
            own_epoch,
            receivers: HashMap::new(),
        }
    }

    /// `receiver` reports `report`: the messages it newly counts as lost (0 for a copy,
    /// an older report, one about another run of this line, or a receiver beyond
    /// [`LOSS_LINES`]). A receiver's count is taken as at most `sent`, the messages this
    /// run of the line has put on the bus: a line that claims more is wrong or lying, and
    /// could otherwise run the sum past `u64::MAX`.
    pub fn take(&mut self, receiver: &str, report: LossReport, sent: u64) -> u64 {
        if report.origin_epoch != self.own_epoch {
            return 0;
        }
        if !self.receivers.contains_key(receiver) {
            if self.receivers.len() >= LOSS_LINES {
                return 0;
            }
            self.receivers.insert(receiver.to_owned(), (0, 0));
        }
        let Some((epoch, last)) = self.receivers.get_mut(receiver) else {
            return 0;
        };
        if report.receiver_epoch != *epoch {
            if report.receiver_epoch < *epoch {
                return 0;
            }
            // The receiver (re)started: it counts from 0.
            (*epoch, *last) = (report.receiver_epoch, 0);
        }
        let lost = report.lost.min(sent);
        let new = lost.saturating_sub(*last);
        *last = (*last).max(lost);
        new
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(origin_epoch: u64, receiver_epoch: u64, lost: u64) -> LossReport {
        LossReport {
            origin_epoch,
            receiver_epoch,
            lost,
        }
    }

    #[test]
    fn a_report_reads_back_and_nothing_else_does() {
        let r = report(1, u64::MAX, 42);
        assert_eq!(LossReport::decode(&r.encode()), Some(r));
        assert_eq!(LossReport::decode(&r.encode()[..23]), None);
        assert_eq!(LossReport::decode(&[0; 25]), None);
        assert_eq!(LossReport::decode(&[]), None);
    }

    #[test]
    fn the_receiver_reports_what_moved_per_origin_run() {
        let mut t = LossTally::default();
        assert!(t.add("line-a", 10, 3));
        assert!(t.add("line-a", 10, 2));
        assert!(t.add("line-b", 7, 1));
        let mut moved = t.reports(99, false);
        moved.sort_by(|x, y| x.0.cmp(&y.0));
        assert_eq!(
            moved,
            vec![
                ("line-a".to_owned(), report(10, 99, 5)),
                ("line-b".to_owned(), report(7, 99, 1))
            ]
        );
        assert!(t.reports(99, false).is_empty(), "nothing moved since");
        assert_eq!(t.reports(99, true).len(), 2, "everything, again");
        assert!(t.add("line-a", 9, 4), "an earlier run: not counted");
        assert!(t.reports(99, false).is_empty());
        t.add("line-a", 11, 1);
        assert_eq!(
            t.reports(99, false),
            vec![("line-a".to_owned(), report(11, 99, 1))],
            "line A restarted: its count starts again"
        );
    }

    #[test]
    fn the_receiver_counts_for_a_bounded_number_of_origins() {
        let mut t = LossTally::default();
        for i in 0..LOSS_LINES {
            assert!(t.add(&format!("l{i}"), 1, 1));
        }
        assert!(!t.add("one-more", 1, 1));
        assert!(t.add("l0", 1, 1), "a known origin still counts");
        assert_eq!(t.reports(1, false).len(), LOSS_LINES);
    }

    const SENT: u64 = 1_000;

    #[test]
    fn the_origin_adds_each_receivers_news_once() {
        let mut r = Reported::new(10);
        assert_eq!(r.take("line-b", report(10, 1, 5), SENT), 5);
        assert_eq!(r.take("line-b", report(10, 1, 5), SENT), 0, "a copy");
        assert_eq!(
            r.take("line-b", report(10, 1, 4), SENT),
            0,
            "an older report"
        );
        assert_eq!(r.take("line-b", report(10, 1, 8), SENT), 3);
        assert_eq!(
            r.take("line-c", report(10, 3, 2), SENT),
            2,
            "another receiver"
        );
        assert_eq!(
            r.take("line-b", report(9, 1, 100), SENT),
            0,
            "about an earlier run"
        );
        assert_eq!(r.take("line-b", report(10, 2, 1), SENT), 1, "B restarted");
        assert_eq!(
            r.take("line-b", report(10, 1, 50), SENT),
            0,
            "B's earlier run, late"
        );
        for i in 0..LOSS_LINES {
            r.take(&format!("l{i}"), report(10, 1, 1), SENT);
        }
        assert_eq!(r.take("one-more", report(10, 1, 1), SENT), 0, "bounded");
        assert_eq!(
            r.take("line-b", report(10, 2, 2), SENT),
            1,
            "a known one still counts"
        );
        assert_eq!(
            r.take("line-b", report(10, 2, u64::MAX), 7),
            5,
            "no more than this line sent"
        );
        assert_eq!(r.take("line-b", report(10, 2, u64::MAX), 7), 0);
    }
}
