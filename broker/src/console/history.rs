//! The recent values of each typed port, for the console's trends (issue 37): "what did
//! the oven temperature do in the last ten minutes", "when did the conveyor stop".
//!
//! **What is kept.** One series per output port whose values are numbers: a data output
//! of an elementary numeric type or BOOL (1/0), an event output (each occurrence is a
//! point whose value is its `seq`), and every such data output carried as an event's WITH
//! data. Strings, dates, times and arrays are shown as last values only. A point is the
//! time the console received the value (ms since 1970, UTC) and the value as an `f64`:
//! 16 bytes. A port gets a point per value the console reads, and of several values of a
//! port in one read of its link (a burst: all within a millisecond or two), the newest
//! (`activity::Newest`). The device's own `ts` of an event is not used as the time: it is whatever
//! the device's clock says, and a series must stay in order to be cut by time.
//!
//! **Bounded, fairly.** A series holds at most `[console] history_points_per_port` points
//! (default 3,600: an hour at one value per second) and none older than
//! `history_window_s` (default 3,600 s). All series together hold at most
//! `history_max_points` (default 2,000,000: 32 MB of points): when more series would need
//! more, each series's share shrinks to `history_max_points / series`, so a port
//! publishing 100 times a second takes no more than a port publishing once a minute, and
//! a device that declares many ports cannot starve the others' history of memory. A
//! series is refused only when even [`MIN_POINTS`] each would not fit (counted in
//! `fbbus_console_dropped_total{what="history_ports"}`). A forgotten device's series go
//! with it; a port a new declaration removes or retypes loses its series.

use std::collections::{HashMap, VecDeque};

use fb_bridge::{DataType, Interface, OutputPort, Value};
use serde::Serialize;

/// The fewest points a series is ever cut to; series beyond `max_points / MIN_POINTS`
/// are not kept.
pub const MIN_POINTS: usize = 16;
/// Bytes of one point in memory.
pub const POINT_BYTES: usize = std::mem::size_of::<Point>();

/// `[console] history_*`.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Points older than this many milliseconds are dropped.
    pub window_ms: u64,
    pub points_per_port: usize,
    pub max_points: usize,
}

/// What a series is of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// A data output published on its own topic.
    Data,
    /// An event output: one point per occurrence, its value the occurrence's `seq`.
    Event,
    /// A data output carried as an event's WITH data.
    With,
}

/// One value: (ms since 1970 UTC when received, value); serialized as `[t, v]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Point(pub u64, pub f64);

/// One port's recent values, oldest first.
#[derive(Debug)]
pub struct Series {
    pub kind: Kind,
    /// The port's declared type; None for an event.
    pub ty: Option<DataType>,
    points: VecDeque<Point>,
    /// Points ever added: what a reader that saw `n` of them has not seen is the last
    /// `pushed - n` ([`Series::after`]).
    pushed: u64,
}

impl Series {
    /// Points with `from <= t <= to`, the newest `limit` of them, oldest first.
    pub fn range(&self, from: u64, to: u64, limit: usize) -> Vec<Point> {
        let start = self.points.partition_point(|p| p.0 < from);
        let end = self.points.partition_point(|p| p.0 <= to);
        let start = start.max(end.saturating_sub(limit));
        self.points.range(start..end.max(start)).copied().collect()
    }

    /// The points added after the first `seen` ever added, the newest `limit` of those.
    pub fn after(&self, seen: u64, limit: usize) -> impl Iterator<Item = &Point> {
        let new = usize::try_from(self.pushed.saturating_sub(seen)).unwrap_or(usize::MAX);
        let n = new.min(self.points.len()).min(limit);
        self.points.range(self.points.len() - n..)
    }

    /// Whether this series is still of `port` (after a new declaration): the same kind
    /// and type.
    pub fn fits(&self, port: Option<OutputPort<'_>>) -> bool {
        match (self.kind, port) {
            (Kind::Event, Some(OutputPort::Event(_))) => true,
            (Kind::Data | Kind::With, Some(OutputPort::Data(t))) => self.ty == Some(t),
            _ => false,
        }
    }

    pub fn pushed(&self) -> u64 {
        self.pushed
    }

    #[cfg(test)]
    pub fn len(&self) -> usize {
        self.points.len()
    }
}

/// Whether values of `ty` are kept as points.
pub fn plottable(ty: DataType) -> bool {
    match ty {
        DataType::Array(..) => false,
        DataType::Elementary(t) => t.reads_as_number(),
    }
}

/// The kind of data output `fb.port`'s series: [`Kind::With`] when an event of its FB
/// carries it (whether a value came on its own topic or inside the event: one series
/// either way), else [`Kind::Data`].
pub fn data_kind(interface: &Interface, fb: &str, port: &str) -> Kind {
    let carried = interface.fbs.get(fb).is_some_and(|f| {
        f.events_out
            .values()
            .any(|e| e.with.iter().any(|w| w == port))
    });
    if carried {
        Kind::With
    } else {
        Kind::Data
    }
}

/// `value` as a point's value, if it is one ([`plottable`]).
pub fn number(value: &Value) -> Option<f64> {
    Some(match *value {
        Value::Bool(b) => f64::from(u8::from(b)),
        Value::Sint(n) => f64::from(n),
        Value::Int(n) => f64::from(n),
        Value::Dint(n) => f64::from(n),
        Value::Lint(n) => n as f64,
        Value::Usint(n) | Value::Byte(n) => f64::from(n),
        Value::Uint(n) | Value::Word(n) => f64::from(n),
        Value::Udint(n) | Value::Dword(n) => f64::from(n),
        Value::Ulint(n) | Value::Lword(n) => n as f64,
        Value::Real(x) => f64::from(x),
        Value::Lreal(x) => x,
        _ => return None,
    })
}

/// Points one of `series` series may hold: `points_per_port`, or its fair share of
/// `max_points`, rounded down to one of eight steps per doubling, so that a growing
/// number of series cuts the others (a pass over all of them) a few dozen times, not once
/// per new series.
fn share(limits: Limits, series: usize) -> usize {
    let fair = (limits.max_points / series.max(1)).max(MIN_POINTS);
    let step = match fair.ilog2() {
        bits if bits > 3 => 1 << (bits - 3),
        _ => 1,
    };
    (fair / step * step).min(limits.points_per_port).max(1)
}

/// Whether [`History::push`] kept the point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pushed {
    Kept,
    /// A new series, and no room for one more ([`MIN_POINTS`] each).
    NoRoom,
}

/// Every series, by device, FB and port (looked up without allocating).
pub struct History {
    limits: Limits,
    devices: HashMap<String, HashMap<String, HashMap<String, Series>>>,
    points: usize,
    /// Points the series' buffers have room for (their capacity), over every series.
    room: usize,
    series: usize,
    /// Points one series may hold now: `points_per_port`, or the fair share.
    cap: usize,
}

impl History {
    pub fn new(limits: Limits) -> History {
        History {
            limits,
            devices: HashMap::new(),
            points: 0,
            room: 0,
            series: 0,
            cap: limits.points_per_port,
        }
    }

    /// Points one series may hold now.
    pub fn capacity(&self) -> usize {
        self.cap
    }

    /// Points kept, over every series.
    pub fn points(&self) -> usize {
        self.points
    }

    /// Series kept.
    pub fn series_count(&self) -> usize {
        self.series
    }

    /// Bytes the points' buffers take (their capacity, not only what they hold).
    pub fn bytes(&self) -> usize {
        self.room * POINT_BYTES
    }

    pub fn get(&self, device: &str, fb: &str, port: &str) -> Option<&Series> {
        self.devices.get(device)?.get(fb)?.get(port)
    }

    /// Adds a point to the port's series, making the series if it is new.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        device: &str,
        fb: &str,
        port: &str,
        kind: Kind,
        ty: Option<DataType>,
        point: Point,
    ) -> Pushed {
        let exists = self.get(device, fb, port).is_some_and(|s| s.kind == kind);
        if !exists && self.make(device, fb, port, kind, ty) == Pushed::NoRoom {
            return Pushed::NoRoom;
        }
        let (cap, window) = (self.cap, self.limits.window_ms);
        let Some(series) = self
            .devices
            .get_mut(device)
            .and_then(|d| d.get_mut(fb))
            .and_then(|f| f.get_mut(port))
        else {
            return Pushed::NoRoom;
        };
        let before = series.points.len();
        let room = series.points.capacity();
        while series.points.len() >= cap {
            series.points.pop_front();
        }
        let oldest = point.0.saturating_sub(window);
        while series.points.front().is_some_and(|p| p.0 < oldest) {
            series.points.pop_front();
        }
        // Time never runs backwards in a series (a clock step back): the point is kept at
        // the last point's time, so ranges stay ordered.
        let at = series.points.back().map_or(point.0, |p| p.0.max(point.0));
        if series.points.len() == series.points.capacity() {
            // Grow by doubling up to the cap, not past it; a small cap (a plant's fair
            // share) at once: the whole line's series grow together, and each step
            // leaves every series's old buffer behind as a hole of its size.
            let want = if cap <= 2 * MIN_POINTS {
                cap
            } else {
                (series.points.len() * 2).max(MIN_POINTS).min(cap)
            };
            series
                .points
                .reserve_exact(want.saturating_sub(series.points.len()).max(1));
        }
        series.points.push_back(Point(at, point.1));
        series.pushed += 1;
        self.points = self.points - before + series.points.len();
        self.room = self.room - room + series.points.capacity();
        Pushed::Kept
    }

    /// A new (empty) series; the others' share shrinks to make room for it.
    fn make(
        &mut self,
        device: &str,
        fb: &str,
        port: &str,
        kind: Kind,
        ty: Option<DataType>,
    ) -> Pushed {
        // A series of another kind under the same name (a redeclared port) is replaced.
        self.remove(device, |f, p, _| f == fb && p == port);
        if (self.series + 1).saturating_mul(MIN_POINTS) > self.limits.max_points {
            return Pushed::NoRoom;
        }
        self.series += 1;
        self.reshare();
        self.devices
            .entry(device.to_owned())
            .or_default()
            .entry(fb.to_owned())
            .or_default()
            .insert(
                port.to_owned(),
                Series {
                    kind,
                    ty,
                    points: VecDeque::new(),
                    pushed: 0,
                },
            );
        Pushed::Kept
    }

    /// Recomputes the share; when it shrank, cuts every series to it, so all of them
    /// together never hold more than `max_points`.
    fn reshare(&mut self) {
        let cap = share(self.limits, self.series);
        let shrank = cap < self.cap;
        self.cap = cap;
        if shrank {
            let (mut cut, mut freed) = (0, 0);
            for series in self
                .devices
                .values_mut()
                .flat_map(HashMap::values_mut)
                .flat_map(HashMap::values_mut)
            {
                let over = series.points.len().saturating_sub(cap);
                if over > 0 {
                    let room = series.points.capacity();
                    series.points.drain(..over);
                    series.points.shrink_to(cap);
                    cut += over;
                    freed += room - series.points.capacity();
                }
            }
            self.points -= cut;
            self.room -= freed;
        }
    }

    /// Drops the device's series for which `gone(fb, port)` holds.
    pub fn remove(&mut self, device: &str, gone: impl Fn(&str, &str, &Series) -> bool) {
        let Some(fbs) = self.devices.get_mut(device) else {
            return;
        };
        let (mut points, mut room, mut series) = (0, 0, 0);
        fbs.retain(|fb, ports| {
            ports.retain(|port, s| {
                let drop = gone(fb, port, s);
                if drop {
                    points += s.points.len();
                    room += s.points.capacity();
                    series += 1;
                }
                !drop
            });
            !ports.is_empty()
        });
        if fbs.is_empty() {
            self.devices.remove(device);
        }
        if series > 0 {
            self.points -= points;
            self.room -= room;
            self.series -= series;
            self.cap = share(self.limits, self.series);
        }
    }

    /// Drops the points older than the window at `now_ms`, over every series (a series
    /// that gets no new values keeps none for longer than the window).
    pub fn expire(&mut self, now_ms: u64) {
        let oldest = now_ms.saturating_sub(self.limits.window_ms);
        let (mut cut, mut freed) = (0, 0);
        for series in self
            .devices
            .values_mut()
            .flat_map(HashMap::values_mut)
            .flat_map(HashMap::values_mut)
        {
            let old = series.points.partition_point(|p| p.0 < oldest);
            if old > 0 {
                series.points.drain(..old);
                cut += old;
                let room = series.points.capacity();
                if series.points.len() < room / 4 {
                    series.points.shrink_to_fit();
                    freed += room - series.points.capacity();
                }
            }
        }
        self.points -= cut;
        self.room -= freed;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fb_bridge::ElementaryType;

    const INT: Option<DataType> = Some(DataType::Elementary(ElementaryType::Int));

    fn history(points_per_port: usize, max_points: usize) -> History {
        History::new(Limits {
            window_ms: 3_600_000,
            points_per_port,
            max_points,
        })
    }

    #[test]
    fn a_series_keeps_its_newest_points_up_to_its_cap() {
        let mut h = history(10, 1000);
        for i in 0..25u64 {
            h.push("d", "FB", "P", Kind::Data, INT, Point(1000 + i, i as f64));
        }
        let s = h.get("d", "FB", "P").unwrap();
        assert_eq!(s.len(), 10);
        assert_eq!(s.pushed(), 25);
        assert_eq!(s.range(0, u64::MAX, usize::MAX)[0], Point(1015, 15.0));
        assert_eq!(h.points(), 10);
        assert_eq!(
            h.bytes(),
            h.get("d", "FB", "P").unwrap().points.capacity() * POINT_BYTES
        );
        // The newest 3 within a range, oldest first.
        let r = s.range(1016, 1020, 3);
        assert_eq!(
            r,
            vec![Point(1018, 18.0), Point(1019, 19.0), Point(1020, 20.0)]
        );
        // What a reader that saw 22 points has not seen.
        let new: Vec<_> = s.after(22, 100).copied().collect();
        assert_eq!(
            new,
            vec![Point(1022, 22.0), Point(1023, 23.0), Point(1024, 24.0)]
        );
    }

    #[test]
    fn the_share_shrinks_with_more_series_and_the_total_stays_bounded() {
        let mut h = history(100, 320);
        for i in 0..100u64 {
            h.push("a", "FB", "P", Kind::Data, INT, Point(i, 1.0));
        }
        assert_eq!(h.points(), 100);
        for d in 0..19 {
            let dev = format!("d{d}");
            for i in 0..100u64 {
                h.push(&dev, "FB", "P", Kind::Data, INT, Point(i, 1.0));
            }
            assert!(h.points() <= 320, "{}", h.points());
        }
        assert_eq!(h.series_count(), 20);
        assert_eq!(h.capacity(), 16);
        assert_eq!(h.get("a", "FB", "P").unwrap().len(), 16);
        // No room for a 21st series at 16 points each.
        let refused = h.push("late", "FB", "P", Kind::Data, INT, Point(0, 0.0));
        assert_eq!(refused, Pushed::NoRoom);
        // A forgotten device frees its share.
        h.remove("a", |_, _, _| true);
        assert_eq!(h.series_count(), 19);
        assert_eq!(
            h.push("late", "FB", "P", Kind::Data, INT, Point(0, 0.0)),
            Pushed::Kept
        );
    }

    #[test]
    fn points_older_than_the_window_go() {
        let mut h = History::new(Limits {
            window_ms: 1000,
            points_per_port: 100,
            max_points: 1000,
        });
        for t in [0u64, 500, 900, 1200, 1600] {
            h.push("d", "FB", "P", Kind::Data, INT, Point(t, 1.0));
        }
        assert_eq!(
            h.get("d", "FB", "P").unwrap().len(),
            3,
            "0 and 500 are older than 1600 - 1000"
        );
        h.expire(2000);
        assert_eq!(h.get("d", "FB", "P").unwrap().len(), 2);
        assert_eq!(h.points(), 2);
        // A clock stepping back keeps the series ordered.
        h.push("d", "FB", "P", Kind::Data, INT, Point(10, 2.0));
        let all = h.get("d", "FB", "P").unwrap().range(0, u64::MAX, 10);
        assert_eq!(all.last(), Some(&Point(1600, 2.0)));
    }

    #[test]
    fn numbers_of_every_plottable_type() {
        assert_eq!(number(&Value::Bool(true)), Some(1.0));
        assert_eq!(number(&Value::Sint(-3)), Some(-3.0));
        assert_eq!(number(&Value::Lreal(2.5)), Some(2.5));
        assert_eq!(number(&Value::Ulint(u64::MAX)), Some(u64::MAX as f64));
        assert_eq!(number(&Value::String("1".into())), None);
        assert!(!plottable(DataType::Elementary(ElementaryType::String)));
        assert!(plottable(DataType::Elementary(ElementaryType::Real)));
        assert!(!plottable(DataType::Array(ElementaryType::Real, 3)));
    }
}
