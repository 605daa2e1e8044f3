//! The process's file descriptors, shared out at start: the MQTT listeners'
//! `[broker] max_connections`, the admin endpoint's `[admin] max_connections`, and a
//! reserve for everything else (the store's log, the registry and its journal, watched
//! files, the bus, the listeners' own sockets).
//!
//! Why (issue 21): the admin endpoint's half-sent headers once used up the process's
//! descriptors, and MQTT accepts then failed with "Too many open files" — an error no
//! client is told about, logged per attempt. Now each plane has its share: the soft
//! `RLIMIT_NOFILE` is raised to what the shares need (up to the hard limit, which needs no
//! privilege), and if the hard limit is lower, the MQTT share is cut to what is left and
//! the broker says so at start. A listener whose share is used up refuses the next
//! connection itself, cleanly, counted and logged (`max_connections`), before the kernel
//! would.

/// Descriptors kept for everything that is not a client connection.
pub const RESERVE: u64 = 128;

/// How the descriptors were shared out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    /// The soft limit in force after start.
    pub limit: u64,
    /// MQTT connections at once: `[broker] max_connections`, or less if the limit is
    /// lower than the shares need.
    pub mqtt: usize,
    /// Whether `mqtt` had to be cut below `[broker] max_connections`.
    pub cut: bool,
}

/// Shares out a soft limit `soft` (raisable up to `hard`) between `mqtt` and `admin`
/// connections and [`RESERVE`]; returns the soft limit to set and the shares.
pub fn share(soft: u64, hard: u64, mqtt: usize, admin: usize) -> Budget {
    let need = (mqtt as u64)
        .saturating_add(admin as u64)
        .saturating_add(RESERVE);
    let limit = if soft >= need {
        soft
    } else {
        need.min(hard).max(soft)
    };
    let for_mqtt = limit.saturating_sub(admin as u64).saturating_sub(RESERVE);
    let granted = (mqtt as u64).min(for_mqtt).max(1) as usize;
    Budget {
        limit,
        mqtt: granted,
        cut: granted < mqtt,
    }
}

/// Raises the soft `RLIMIT_NOFILE` as far as `mqtt` + `admin` + [`RESERVE`] need (within
/// the hard limit) and returns the shares. Logs what it did; where the limits cannot be
/// read (not Unix), the configured `mqtt` stands.
// `rlim_t` is u64 here, not on every Unix: the casts are needed elsewhere.
#[allow(clippy::unnecessary_cast)]
pub fn apply(mqtt: usize, admin: usize) -> Budget {
    #[cfg(unix)]
    {
        let mut rl = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes one rlimit we own.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut rl) } == 0 {
            let (soft, hard) = (rl.rlim_cur as u64, rl.rlim_max as u64);
            let budget = share(soft, hard, mqtt, admin);
            if budget.limit > soft {
                let raised = libc::rlimit {
                    rlim_cur: budget.limit as libc::rlim_t,
                    rlim_max: rl.rlim_max,
                };
                // SAFETY: setrlimit reads one rlimit we own; raising the soft limit up to
                // the hard one needs no privilege.
                if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } != 0 {
                    let budget = share(soft, soft, mqtt, admin);
                    report(budget, mqtt, admin, soft, hard);
                    return budget;
                }
            }
            report(budget, mqtt, admin, soft, hard);
            return budget;
        }
    }
    Budget {
        limit: u64::MAX,
        mqtt,
        cut: false,
    }
}

fn report(budget: Budget, mqtt: usize, admin: usize, soft: u64, hard: u64) {
    if budget.cut {
        tracing::warn!(
            limit = budget.limit,
            hard_limit = hard,
            max_connections = mqtt,
            mqtt_connections = budget.mqtt,
            admin_connections = admin,
            reserve = RESERVE,
            "the process may open {} files (RLIMIT_NOFILE), fewer than [broker] \
             max_connections + [admin] max_connections + {RESERVE} need: MQTT connections \
             are limited to {} (raise the limit: LimitNOFILE= in the systemd unit, \
             --ulimit nofile= for a container, ulimit -n; or lower max_connections)",
            budget.limit,
            budget.mqtt,
        );
    } else if budget.limit > soft {
        tracing::info!(
            from = soft,
            to = budget.limit,
            "raised the open-file limit (RLIMIT_NOFILE) to what the connection limits need"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn enough_is_left_alone() {
        assert_eq!(
            share(100_000, 100_000, 4096, 64),
            Budget {
                limit: 100_000,
                mqtt: 4096,
                cut: false
            }
        );
    }

    #[test]
    fn the_soft_limit_is_raised_within_the_hard_one() {
        let need = 4096 + 64 + RESERVE;
        assert_eq!(share(1024, 1 << 20, 4096, 64).limit, need);
        assert!(!share(1024, 1 << 20, 4096, 64).cut);
    }

    #[test]
    fn below_the_hard_limit_mqtt_gets_what_is_left() {
        let b = share(1024, 1024, 4096, 64);
        assert_eq!(b.limit, 1024);
        assert_eq!(b.mqtt, (1024 - 64 - RESERVE) as usize);
        assert!(b.cut);
        // A limit below even the reserve leaves MQTT one connection, not none.
        assert_eq!(share(10, 10, 4096, 64).mqtt, 1);
    }
}
