//! Counting at a subscriber: which messages of the current batch arrived, how often, in
//! what order, and how late.
//!
//! A batch gives each publisher (a *stream*) a range of sequence numbers. A message is
//! recorded by its stream and `seq`: the first copy counts as delivered, later copies as
//! duplicates; one that arrives after a higher `seq` of its stream is out of order;
//! anything outside the current batch's ranges (late arrivals of an earlier batch, other
//! traffic) is counted as stale and otherwise ignored.

use hdrhistogram::Histogram;

use crate::model::Latency;

/// Highest latency the histograms hold: one hour, in microseconds.
const MAX_LATENCY_US: u64 = 3_600_000_000;

/// One subscriber's counts for the current batch.
pub struct Tally {
    streams: Vec<Stream>,
    latency: Histogram<u64>,
    delivered: u64,
    duplicates: u64,
    out_of_order: u64,
    stale: u64,
    first_us: Option<u64>,
    last_us: Option<u64>,
}

struct Stream {
    /// The batch's seqs are `base..base + len`.
    base: u64,
    len: u64,
    seen: Vec<u64>,
    highest: Option<u64>,
}

impl Stream {
    fn empty() -> Stream {
        Stream {
            base: 0,
            len: 0,
            seen: Vec::new(),
            highest: None,
        }
    }
}

/// A finished batch as one subscriber saw it.
#[derive(Debug, Clone)]
pub struct Counts {
    pub delivered: u64,
    pub duplicates: u64,
    pub out_of_order: u64,
    pub stale: u64,
    pub first_us: Option<u64>,
    pub last_us: Option<u64>,
    pub latency: Histogram<u64>,
}

/// An empty latency histogram with the harness's resolution.
pub fn histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, MAX_LATENCY_US, 3).expect("valid histogram bounds")
}

impl Default for Tally {
    fn default() -> Tally {
        Tally::new(0)
    }
}

impl Tally {
    pub fn new(streams: usize) -> Tally {
        Tally {
            streams: (0..streams).map(|_| Stream::empty()).collect(),
            latency: histogram(),
            delivered: 0,
            duplicates: 0,
            out_of_order: 0,
            stale: 0,
            first_us: None,
            last_us: None,
        }
    }

    /// Starts a batch: stream `i` will send seqs `ranges[i].0 .. ranges[i].0 + ranges[i].1`.
    pub fn begin(&mut self, ranges: &[(u64, u64)]) {
        *self = Tally::new(ranges.len());
        for (stream, &(base, len)) in self.streams.iter_mut().zip(ranges) {
            stream.base = base;
            stream.len = len;
            stream.seen = vec![0; len.div_ceil(64) as usize];
        }
    }

    /// Records one message of `stream` with `seq`, published at `sent_us`, received at
    /// `now_us`.
    pub fn record(&mut self, stream: usize, seq: u64, sent_us: u64, now_us: u64) {
        let Some(s) = self.streams.get_mut(stream) else {
            self.stale += 1;
            return;
        };
        if seq < s.base || seq >= s.base + s.len {
            self.stale += 1;
            return;
        }
        let i = (seq - s.base) as usize;
        let (word, bit) = (i / 64, 1u64 << (i % 64));
        if s.seen[word] & bit != 0 {
            self.duplicates += 1;
            return;
        }
        s.seen[word] |= bit;
        if s.highest.is_some_and(|h| seq < h) {
            self.out_of_order += 1;
        } else {
            s.highest = Some(seq);
        }
        self.delivered += 1;
        self.latency
            .saturating_record(now_us.saturating_sub(sent_us).max(1));
        self.first_us = Some(self.first_us.map_or(now_us, |f| f.min(now_us)));
        self.last_us = Some(self.last_us.map_or(now_us, |l| l.max(now_us)));
    }

    pub fn delivered(&self) -> u64 {
        self.delivered
    }

    /// The counts so far.
    pub fn counts(&self) -> Counts {
        Counts {
            delivered: self.delivered,
            duplicates: self.duplicates,
            out_of_order: self.out_of_order,
            stale: self.stale,
            first_us: self.first_us,
            last_us: self.last_us,
            latency: self.latency.clone(),
        }
    }
}

/// The model's latency summary of a histogram.
pub fn summarize(h: &Histogram<u64>) -> Latency {
    if h.is_empty() {
        return Latency::default();
    }
    let curve = [
        0.0, 10.0, 25.0, 50.0, 75.0, 90.0, 95.0, 99.0, 99.5, 99.9, 99.95, 99.99, 99.999, 100.0,
    ]
    .iter()
    .map(|&p| (p, h.value_at_quantile(p / 100.0)))
    .collect();
    Latency {
        count: h.len(),
        mean_us: h.mean(),
        p50_us: h.value_at_quantile(0.50),
        p90_us: h.value_at_quantile(0.90),
        p99_us: h.value_at_quantile(0.99),
        p999_us: h.value_at_quantile(0.999),
        max_us: h.max(),
        curve,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_delivered_duplicates_order_and_stale() {
        let mut t = Tally::default();
        t.begin(&[(1, 100), (50, 10)]);
        for seq in 1..=100 {
            if seq % 10 != 0 {
                t.record(0, seq, 1000, 1000 + seq);
            }
        }
        t.record(0, 5, 1000, 2000); // duplicate
        t.record(0, 500, 1000, 2000); // not this batch
        t.record(7, 1, 1000, 2000); // unknown stream
        t.record(1, 55, 1000, 1100);
        t.record(1, 52, 1000, 1100); // after 55: out of order
        let c = t.counts();
        assert_eq!(c.delivered, 90 + 2);
        assert_eq!(c.duplicates, 1);
        assert_eq!(c.stale, 2);
        assert_eq!(c.out_of_order, 1);
        assert_eq!(c.first_us, Some(1001));
        assert_eq!(c.last_us, Some(1100));
        assert_eq!(c.latency.len(), 92);
        let l = summarize(&c.latency);
        assert_eq!(l.max_us, 100);
        assert_eq!(l.curve.last(), Some(&(100.0, 100)));
    }
}
