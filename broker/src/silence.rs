//! Silence: a device that is connected but whose outputs stopped.
//!
//! A 4diac FORTE whose MQTT send failed (a broker restart, a network cut) reconnects, but
//! its publishers stay dead: the registry sees it `online` while nothing it should publish
//! arrives. So the registry also judges whether a local online device still speaks.
//!
//! **The rule.** Every accepted typed publication on one of the device's declared outputs
//! is timed ([`Activity::published`]). Per port, the intervals between publications feed
//! the estimator of RFC 6298 (TCP's retransmission timer): a smoothed mean (gain 1/8) and
//! a smoothed mean deviation (gain 1/4). A port has a **period** once it has shown
//! [`MIN_INTERVALS`] intervals and its deviation is at most [`MAX_DEVIATION`] of its mean:
//! an event output that fires when something happens has no period and never makes a
//! healthy device silent. A device is **silent** when it has at least one port with a
//! period and none of those ports has published for more than
//! `max(silence_factor × period, silence_min_s)`, counted from its last publication or from
//! the start of the current connection, whichever is later (a device that just came back
//! gets a full bound to speak).
//!
//! `silence_factor` defaults to 3: with a deviation of at most half the period, an
//! interval of three periods is four deviations above the mean, which a live publisher
//! does not reach by jitter; it also lets two consecutive QoS 0 messages be lost before
//! the device is called silent. `silence_min_s` (default 5 s) keeps fast ports (10 ms)
//! from turning silent on a scheduling hiccup of the device or of the broker.
//!
//! **Remembered across restarts.** A FORTE whose publishers died at a broker restart
//! never publishes to the new broker, which could then never learn a period. So the
//! observed periods are persisted with the registry ([`Activity::periods`]) and given
//! back to a device's ports when it connects or declares again ([`Activity::remember`]).
//!
//! A gap longer than the bound is a silence, not an interval: when the port speaks again
//! the gap is not fed to the estimator, so the period it had still holds.
//!
//! **Later: profiles.** A device profile (issue 16) that states a port's period sets it
//! with [`Activity::state_period`]; a stated period is used instead of the observed one
//! and counts from the first publication on.
//!
//! Cost on the hot path: one uncontended lock of the device's own [`Activity`] and two
//! map lookups per accepted typed publication; the registry's lock is not taken. Only
//! declared outputs are timed, so the state is bounded by the declaration limits.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use fb_bridge::Interface;
use tokio::sync::Notify;

/// Intervals a port must show before it can have an observed period.
pub const MIN_INTERVALS: u32 = 5;
/// The largest smoothed deviation, as a fraction of the mean, of a port with a period.
pub const MAX_DEVIATION: f64 = 0.5;
/// The gain of the smoothed mean (RFC 6298's alpha).
const MEAN_GAIN: f64 = 1.0 / 8.0;
/// The gain of the smoothed deviation (RFC 6298's beta).
const DEVIATION_GAIN: f64 = 1.0 / 4.0;

/// How long a periodic output may be quiet (`[fb] silence_factor`, `silence_min_s`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bound {
    /// Multiples of a port's period; 0 turns the judgement off.
    pub factor: f64,
    /// The bound is never shorter than this.
    pub floor: Duration,
}

impl Bound {
    /// `[fb]`'s defaults: three periods, and never less than 5 s.
    pub const DEFAULT: Bound = Bound {
        factor: 3.0,
        floor: Duration::from_secs(5),
    };

    pub fn enabled(&self) -> bool {
        self.factor > 0.0
    }

    /// How long a port with `period` may be quiet.
    pub fn for_period(&self, period: Duration) -> Duration {
        period.mul_f64(self.factor.max(0.0)).max(self.floor)
    }
}

/// One output port's publication times and period.
#[derive(Debug, Default, Clone)]
struct PortClock {
    last: Option<Instant>,
    /// Smoothed interval and its smoothed deviation, in seconds.
    mean: f64,
    deviation: f64,
    intervals: u32,
    /// The period a profile states for this port; used instead of the observed one.
    stated: Option<Duration>,
}

impl PortClock {
    fn published(&mut self, now: Instant, bound: &Bound) {
        if let Some(last) = self.last {
            let interval = now.saturating_duration_since(last);
            let gap = self
                .period()
                .is_some_and(|period| interval > bound.for_period(period));
            if !gap {
                self.observe(interval.as_secs_f64());
            }
        }
        self.last = Some(now);
    }

    fn observe(&mut self, interval: f64) {
        if self.intervals == 0 {
            self.mean = interval;
            self.deviation = interval / 2.0;
        } else {
            self.deviation += DEVIATION_GAIN * ((self.mean - interval).abs() - self.deviation);
            self.mean += MEAN_GAIN * (interval - self.mean);
        }
        self.intervals = self.intervals.saturating_add(1);
    }

    /// The port's period: stated, or observed once regular; None for an event-like port.
    fn period(&self) -> Option<Duration> {
        if self.stated.is_some() {
            return self.stated;
        }
        let regular = self.intervals >= MIN_INTERVALS
            && self.mean > 0.0
            && self.deviation <= MAX_DEVIATION * self.mean;
        regular
            .then(|| Duration::try_from_secs_f64(self.mean).ok())
            .flatten()
    }
}

/// Observed periods in seconds, by FB and port: what the registry file keeps.
pub type Periods = BTreeMap<String, BTreeMap<String, f64>>;

/// What the judgement found about one device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// No port has a period: nothing to judge.
    NoPeriod,
    /// A periodic port published within its bound.
    Speaking,
    /// Every periodic port is quiet beyond its bound, since this instant (the latest
    /// publication of any of them, or the start of the connection).
    Silent { since: Instant },
}

/// One local device's output activity, shared by its connection (which times
/// publications) and the registry (which judges it every second).
#[derive(Debug)]
pub struct Activity {
    inner: Mutex<Ports>,
    /// The registry ended the device for its silence and its broker-side will is still to
    /// be published, by one of its connections ([`Activity::take_will_due`]).
    will_due: AtomicBool,
    /// Wakes the device's connections when the registry ended it ([`Activity::ended`]).
    ended: Notify,
}

#[derive(Debug)]
struct Ports {
    /// By FB, then port: the declared outputs (data and event).
    clocks: BTreeMap<String, BTreeMap<String, PortClock>>,
    /// When the current connection started.
    connected: Instant,
    /// How long the device may be silent before it is offline (a profile's
    /// `liveness.offline_after_silent_s`); None: never for silence.
    offline_after: Option<Duration>,
    /// The registry marked the device offline for its silence; its next accepted
    /// publication brings it back.
    ended: bool,
}

impl Activity {
    /// Timing for the outputs `interface` declares, connected since `now`.
    pub fn new(interface: &Interface, now: Instant) -> Activity {
        let mut clocks: BTreeMap<String, BTreeMap<String, PortClock>> = BTreeMap::new();
        for (fb, port) in interface.outputs() {
            clocks
                .entry(fb.to_owned())
                .or_default()
                .insert(port.to_owned(), PortClock::default());
        }
        Activity {
            inner: Mutex::new(Ports {
                clocks,
                connected: now,
                offline_after: None,
                ended: false,
            }),
            will_due: AtomicBool::new(false),
            ended: Notify::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Ports> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The device connected again at `now`: its ports keep their periods, and the bound
    /// counts from now.
    pub fn reconnected(&self, now: Instant) {
        let mut ports = self.lock();
        ports.connected = now;
        ports.ended = false;
        self.will_due.store(false, Ordering::Relaxed);
    }

    /// An accepted typed publication on `fb.port` at `now`; ignored for a port the
    /// device did not declare as an output. Returns true when the registry had ended the
    /// device for its silence: it speaks again, and its connection tells the registry.
    pub fn published(&self, fb: &str, port: &str, now: Instant, bound: &Bound) -> bool {
        let mut ports = self.lock();
        if let Some(clock) = ports.clocks.get_mut(fb).and_then(|f| f.get_mut(port)) {
            clock.published(now, bound);
        }
        if ports.ended {
            ports.ended = false;
            ports.connected = now;
            self.will_due.store(false, Ordering::Relaxed);
            return true;
        }
        false
    }

    /// A profile's `liveness.offline_after_silent_s`: silent that long, the device is
    /// offline ([`Activity::end_if_silent_for`]).
    pub fn set_offline_after(&self, after: Option<Duration>) {
        self.lock().offline_after = after;
    }

    /// The registry found the device silent since `since`: if that is longer than its
    /// `offline_after`, the device ends now (once, until it speaks or connects again),
    /// its will falls due and its connections are woken. Returns whether it ended.
    pub fn end_if_silent_for(&self, now: Instant, since: Instant) -> bool {
        let mut ports = self.lock();
        let due = ports
            .offline_after
            .is_some_and(|after| now.saturating_duration_since(since) >= after);
        if !due || ports.ended {
            return false;
        }
        ports.ended = true;
        drop(ports);
        self.will_due.store(true, Ordering::Release);
        self.ended.notify_waiters();
        true
    }

    /// Resolves when the registry ends the device for its silence (a connection waits on
    /// it beside its socket; it may miss a wake while busy, so it also asks
    /// [`Activity::take_will_due`] after every wake).
    pub fn ended(&self) -> tokio::sync::futures::Notified<'_> {
        self.ended.notified()
    }

    /// True once per silence ending: the connection that gets it publishes the device's
    /// broker-side will.
    pub fn take_will_due(&self) -> bool {
        self.will_due.load(Ordering::Relaxed) && self.will_due.swap(false, Ordering::Acquire)
    }

    /// The observed periods of the ports that have one.
    pub fn periods(&self) -> Periods {
        let ports = self.lock();
        let mut out = Periods::new();
        for (fb, clocks) in &ports.clocks {
            for (port, clock) in clocks {
                if clock.stated.is_none() && clock.period().is_some() {
                    out.entry(fb.clone())
                        .or_default()
                        .insert(port.clone(), clock.mean);
                }
            }
        }
        out
    }

    /// Gives declared ports the periods observed before (another connection, another
    /// broker run): they count at once. Ports no longer declared, and values that are no
    /// period (not positive, over a day), are ignored.
    pub fn remember(&self, periods: &Periods) {
        let mut ports = self.lock();
        for (fb, port, seconds) in periods
            .iter()
            .flat_map(|(fb, p)| p.iter().map(move |(port, s)| (fb, port, *s)))
        {
            let Some(clock) = ports.clocks.get_mut(fb).and_then(|f| f.get_mut(port)) else {
                continue;
            };
            if seconds > 0.0 && seconds <= 86_400.0 && clock.intervals < MIN_INTERVALS {
                clock.mean = seconds;
                clock.deviation = 0.0;
                clock.intervals = MIN_INTERVALS;
            }
        }
    }

    /// A profile states the period of `fb.port` (`periods` in a device profile).
    pub fn state_period(&self, fb: &str, port: &str, period: Duration) {
        let mut ports = self.lock();
        if let Some(clock) = ports.clocks.get_mut(fb).and_then(|f| f.get_mut(port)) {
            clock.stated = Some(period);
        }
    }

    /// Whether the device is silent at `now`.
    pub fn judge(&self, now: Instant, bound: &Bound) -> Verdict {
        let ports = self.lock();
        let mut verdict = Verdict::NoPeriod;
        for clock in ports.clocks.values().flat_map(BTreeMap::values) {
            let Some(period) = clock.period() else {
                continue;
            };
            let since = clock
                .last
                .map_or(ports.connected, |l| l.max(ports.connected));
            if now.saturating_duration_since(since) <= bound.for_period(period) {
                return Verdict::Speaking;
            }
            verdict = match verdict {
                Verdict::Silent { since: s } => Verdict::Silent {
                    since: s.max(since),
                },
                _ => Verdict::Silent { since },
            };
        }
        verdict
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOUND: Bound = Bound {
        factor: 3.0,
        floor: Duration::from_secs(1),
    };

    fn interface() -> Interface {
        serde_json::from_value(serde_json::json!({"fbs": {"CONV": {
            "events_out": {"CNF": {"with": ["SPEED"]}, "ALARM": {}},
            "data_out": {"SPEED": "REAL"},
        }}}))
        .unwrap()
    }

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Publishes on `port` every `period` for `n` publications from `start`; returns the
    /// time of the last.
    fn every(a: &Activity, port: &str, start: Instant, period: Duration, n: u32) -> Instant {
        let mut t = start;
        for i in 0..n {
            t = start + period * i;
            a.published("CONV", port, t, &BOUND);
        }
        t
    }

    #[test]
    fn a_periodic_port_that_stops_makes_the_device_silent_after_the_bound() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        assert_eq!(a.judge(t0, &BOUND), Verdict::NoPeriod);
        let last = every(&a, "SPEED", t0, ms(200), 20);
        // 3 × 200 ms is below the 1 s floor: the bound is 1 s.
        assert_eq!(a.judge(last + ms(1000), &BOUND), Verdict::Speaking);
        assert_eq!(
            a.judge(last + ms(1001), &BOUND),
            Verdict::Silent { since: last }
        );
        // Speaking again ends it at once, and the gap did not change the period.
        let back = last + ms(10_000);
        a.published("CONV", "SPEED", back, &BOUND);
        assert_eq!(a.judge(back, &BOUND), Verdict::Speaking);
        assert_eq!(
            a.judge(back + ms(1001), &BOUND),
            Verdict::Silent { since: back }
        );
    }

    #[test]
    fn a_device_allowed_so_much_silence_ends_once_and_comes_back_when_it_speaks() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        let last = every(&a, "SPEED", t0, ms(200), 10);
        let Verdict::Silent { since } = a.judge(last + ms(1500), &BOUND) else {
            panic!("silent");
        };
        // Without an allowance, silence never ends a device.
        assert!(!a.end_if_silent_for(last + ms(60_000), since));
        a.set_offline_after(Some(ms(3000)));
        assert!(!a.end_if_silent_for(last + ms(2999), since));
        assert!(!a.take_will_due());
        assert!(a.end_if_silent_for(last + ms(3000), since));
        assert!(!a.end_if_silent_for(last + ms(4000), since), "once");
        assert!(a.take_will_due());
        assert!(!a.take_will_due(), "one connection publishes the will");
        // Its next publication brings it back, and a later silence ends it again.
        let back = last + ms(10_000);
        assert!(a.published("CONV", "SPEED", back, &BOUND));
        assert!(!a.published("CONV", "SPEED", back + ms(200), &BOUND));
        assert!(a.end_if_silent_for(back + ms(3200), back + ms(200)));
    }

    #[test]
    fn the_bound_is_the_factor_times_the_period_above_the_floor() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        let last = every(&a, "SPEED", t0, ms(2000), 8);
        assert_eq!(a.judge(last + ms(6000), &BOUND), Verdict::Speaking);
        assert!(matches!(
            a.judge(last + ms(6001), &BOUND),
            Verdict::Silent { .. }
        ));
    }

    #[test]
    fn too_few_intervals_are_no_period() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        let last = every(&a, "SPEED", t0, ms(200), MIN_INTERVALS);
        assert_eq!(a.judge(last + ms(60_000), &BOUND), Verdict::NoPeriod);
        a.published("CONV", "SPEED", last + ms(200), &BOUND);
        assert!(matches!(
            a.judge(last + ms(60_000), &BOUND),
            Verdict::Silent { .. }
        ));
    }

    #[test]
    fn an_irregular_event_port_has_no_period() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        let mut t = t0;
        for gap in [
            50, 3000, 120, 9000, 400, 20, 7000, 300, 15_000, 60, 2500, 80,
        ] {
            t += ms(gap);
            a.published("CONV", "ALARM", t, &BOUND);
        }
        assert_eq!(a.judge(t + ms(600_000), &BOUND), Verdict::NoPeriod);
    }

    #[test]
    fn the_device_speaks_while_any_periodic_port_does() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        every(&a, "SPEED", t0, ms(200), 20);
        let cnf = every(&a, "CNF", t0, ms(500), 40);
        // SPEED stopped at 3.8 s; CNF goes on until 19.5 s.
        assert_eq!(a.judge(cnf + ms(500), &BOUND), Verdict::Speaking);
        assert_eq!(
            a.judge(cnf + ms(1501), &BOUND),
            Verdict::Silent { since: cnf }
        );
    }

    #[test]
    fn a_new_connection_gets_a_full_bound_and_keeps_the_period() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        let last = every(&a, "SPEED", t0, ms(200), 20);
        let back = last + ms(30_000);
        a.reconnected(back);
        assert_eq!(a.judge(back + ms(1000), &BOUND), Verdict::Speaking);
        assert_eq!(
            a.judge(back + ms(1001), &BOUND),
            Verdict::Silent { since: back }
        );
    }

    #[test]
    fn a_stated_period_counts_from_the_first_publication() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        a.state_period("CONV", "SPEED", ms(1000));
        a.published("CONV", "SPEED", t0, &BOUND);
        assert_eq!(a.judge(t0 + ms(3000), &BOUND), Verdict::Speaking);
        assert!(matches!(
            a.judge(t0 + ms(3001), &BOUND),
            Verdict::Silent { .. }
        ));
    }

    #[test]
    fn remembered_periods_count_at_once() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        every(&a, "SPEED", t0, ms(200), 20);
        every(&a, "ALARM", t0, ms(7), 2);
        let periods = a.periods();
        assert_eq!(periods.len(), 1);
        assert!(
            (periods["CONV"]["SPEED"] - 0.2).abs() < 0.001,
            "{periods:?}"
        );

        // A broker restart: the device reconnects and never publishes.
        let later = t0 + ms(600_000);
        let b = Activity::new(&interface(), later);
        let mut odd = periods.clone();
        odd.entry("CONV".into())
            .or_default()
            .insert("CNF".into(), f64::NAN);
        odd.entry("GONE".into())
            .or_default()
            .insert("X".into(), 1.0);
        b.remember(&odd);
        assert_eq!(b.judge(later + ms(1000), &BOUND), Verdict::Speaking);
        assert_eq!(
            b.judge(later + ms(1001), &BOUND),
            Verdict::Silent { since: later }
        );
        assert_eq!(b.periods(), periods);
    }

    #[test]
    fn undeclared_ports_are_not_timed() {
        let t0 = Instant::now();
        let a = Activity::new(&interface(), t0);
        let last = every(&a, "NOPE", t0, ms(200), 20);
        assert_eq!(a.judge(last + ms(60_000), &BOUND), Verdict::NoPeriod);
    }
}
