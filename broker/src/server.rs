//! Assembly: builds the broker from a validated [`Config`], binds everything, and runs until
//! shutdown. Reading this file top to bottom tells what a running fbbus consists of.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use security::{AclRules, PasswordFile};
use tokio::net::{TcpListener, TcpSocket};
use tokio::sync::{watch, Semaphore};
use tokio_rustls::TlsAcceptor;

use crate::admin::{self, AdminState};
use crate::admin_auth::AdminAuth;
use crate::authenticator::Authenticator;
use crate::broker_publisher::{BrokerPublisher, INTERNAL_CLIENT_ID};
use crate::config::Config;
use crate::health::{Health, Probe, PROBE_CLIENT_ID};
use crate::identity::Identities;
use crate::listener::Listener;
use crate::metrics::Metrics;
use crate::observer::Observers;
use crate::policy::access::Access;
use crate::policy::typed::FbTopics;
use crate::policy::PublishPolicy;
use crate::profiles::Profiles;
use crate::registry::Registry;
use crate::router::RouterHandle;
use crate::session::lifetime::purge_evicted;
use crate::session::redelivery::Redeliveries;
use crate::session::table::SessionTable;
use crate::session::Context;
use crate::session::ListenerPolicy;
use crate::store::{Restore, Store};
use crate::supervisor::Tasks;
use crate::watched_file::WatchedFile;
use crate::wills::Wills;

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// `message` names the file (the loaders' errors do).
    #[error("{kind}: {message}")]
    File {
        kind: &'static str,
        path: String,
        message: String,
    },
    #[error("listener `{name}`: cannot bind {addr}: {source}")]
    Bind {
        name: String,
        addr: SocketAddr,
        source: std::io::Error,
    },
    #[error("listener `{name}`: {source}")]
    Tls {
        name: String,
        source: crate::tls::TlsError,
    },
    #[error("router: {0}")]
    Router(String),
    #[error("cannot start the password verification threads: {0}")]
    Verifier(std::io::Error),
    #[cfg(feature = "bridge")]
    #[error(transparent)]
    Bridge(#[from] crate::bridge::BridgeError),
}

/// A running broker.
pub struct Broker {
    /// (listener name, bound address), in config order.
    pub listeners: Vec<(String, SocketAddr)>,
    pub admin: SocketAddr,
    pub metrics: Arc<Metrics>,
    shutdown: watch::Sender<bool>,
    health: Arc<Health>,
    /// Every task the broker spawned, finished on shutdown.
    tasks: Tasks,
    registry: Arc<Registry>,
    store: Option<Arc<Store>>,
    /// The Sparkplug view, whose NDEATH goes out before the clients' connections close.
    sparkplug: Option<Arc<crate::sparkplug::View>>,
    #[cfg(feature = "bridge")]
    bridge: Option<Arc<crate::bridge::Bridge>>,
}

impl Broker {
    /// Binds every listener and the admin endpoint and starts serving.
    /// Must run inside a multi-threaded tokio runtime.
    pub async fn start(config: Config) -> Result<Broker, StartError> {
        let metrics = Arc::new(Metrics::new());
        let health = Health::new();
        let tasks = Tasks::new(&health);

        let Files {
            passwords,
            acl,
            admin_passwords,
            mut tls,
            profiles,
        } = Files::load(&config)?;
        let authenticator = Arc::new(
            Authenticator::new(&config.auth, passwords.clone(), Arc::clone(&metrics))
                .map_err(StartError::Verifier)?,
        );

        let router = RouterHandle::spawn(&config.broker.router(), Arc::clone(&metrics), &health);
        let internal = router
            .link(INTERNAL_CLIENT_ID, true, 0)
            .await
            .map_err(|e| StartError::Router(e.to_string()))?;
        let publisher = BrokerPublisher::start((internal.0, internal.1), &tasks);
        crate::sys::start(
            Duration::from_secs(config.broker.sys_interval_s),
            Arc::clone(&metrics),
            Arc::clone(&publisher),
            &tasks,
        );
        let probe = router
            .link(PROBE_CLIENT_ID, true, 0)
            .await
            .map_err(|e| StartError::Router(e.to_string()))?;
        let (probe, probe_task) = Probe::start((probe.0, probe.1));
        tasks.spawn(probe_task);
        health.set_probe(probe);
        let wills = Wills::new(Arc::clone(&publisher), Arc::clone(&metrics), tasks.clone());
        let registry_file = &config.fb.registry_file;
        let registry = Registry::open(
            &config.broker.line,
            (!registry_file.as_os_str().is_empty()).then_some(registry_file.as_path()),
            Arc::clone(&publisher),
            Arc::clone(&metrics),
            config.fb.silence_bound(),
            config.fb.registry_limits(),
            &tasks,
        )
        .map_err(|e| StartError::File {
            kind: "device registry",
            path: e.path.clone(),
            message: e.to_string(),
        })?;
        registry.start_periodic_checks(&tasks);
        let (store, restore) = if config.persistence.enabled {
            let (store, restore) = Store::open(
                &config.persistence,
                (
                    config.broker.max_retained_messages,
                    config.broker.max_retained_bytes,
                ),
                &metrics,
            )
            .map_err(|e| StartError::File {
                kind: "store",
                path: crate::store::log_path(&config.persistence.dir)
                    .display()
                    .to_string(),
                message: e.to_string(),
            })?;
            (Some(store), restore)
        } else {
            (None, Restore::default())
        };
        if let Some(store) = &store {
            publisher.set_store(Arc::clone(store));
        }
        // Session numbers continue from the persisted registry, so a device's first
        // connection after a restart is newer than anything the registry remembers.
        let sessions = SessionTable::new(crate::router::saved_sessions_limit(
            config.broker.max_connections,
        ))
        .evicting({
            let (router, tasks, store) = (router.clone(), tasks.clone(), store.clone());
            move |client_id| purge_evicted(&router, &tasks, store.as_ref(), client_id)
        });
        for (_, session) in registry.sessions() {
            sessions.seed(session);
        }

        // The line as a Sparkplug edge node: its own router link, off the packet path but for
        // hosts' commands (the policy's Sparkplug stage).
        let sparkplug = if config.sparkplug.enabled {
            let link = router
                .observer_link(crate::sparkplug::CLIENT_ID)
                .await
                .map_err(|e| StartError::Router(e.to_string()))?;
            Some(crate::sparkplug::start(
                &config,
                Arc::clone(&registry),
                &metrics,
                (link.0, link.1),
            ))
        } else {
            None
        };

        let (shutdown, shutdown_rx) = watch::channel(false);
        let fb = Arc::new(
            FbTopics::new(
                Arc::clone(&registry),
                config.fb.undeclared,
                config.auth.password_file.is_none(),
                config.fb.fbdk_time_unit,
                publisher,
                Arc::clone(&metrics),
            )
            .with_fbdk_max_payload(config.fb.fbdk_max_payload)
            .with_max_packet(config.broker.max_packet_bytes)
            .with_max_devices(config.fb.max_devices)
            .with_limits(config.fb.declaration_limits())
            .with_profiles(Arc::clone(&profiles)),
        );
        // Who is told of subscriptions: typed-topic re-encoding, and the bus bridge, whose
        // handle exists before any client connects (it links the bus once started, below).
        let mut observers = Observers::default();
        observers.register(Arc::clone(&fb) as _);
        if let Some(view) = &sparkplug {
            observers.register(view.readers() as _);
        }
        #[cfg(feature = "bridge")]
        let bridge = match &config.bridge {
            Some(bus) => {
                let bridge = crate::bridge::Bridge::new(bus, &config.broker.line)?;
                observers.register(Arc::clone(&bridge) as _);
                Some(bridge)
            }
            None => None,
        };
        let ctx = Arc::new(Context {
            router,
            authenticator,
            identity: Identities::new(config.auth.password_file.is_some(), config.auth.client_id),
            policy: {
                let policy = PublishPolicy::new(
                    Access::new(acl.clone()),
                    Arc::clone(&fb),
                    Arc::clone(&metrics),
                );
                match &sparkplug {
                    Some(view) => policy.with_sparkplug(crate::sparkplug::command::Commands::new(
                        &config.sparkplug.group,
                        &config.broker.line,
                        config.sparkplug.commands,
                        Arc::clone(view),
                    )),
                    None => policy,
                }
            },
            wills,
            fb,
            sessions,
            clients: Arc::default(),
            takeovers: Default::default(),
            redeliveries: Redeliveries::new(crate::router::saved_sessions_limit(
                config.broker.max_connections,
            )),
            store,
            retained_shares: Arc::new(crate::retained_share::RetainedShares::new(
                config.broker.max_retained_messages_per_identity.max(1),
                config.broker.max_retained_bytes_per_identity.max(1),
                config.broker.max_retained_messages,
            )),
            metrics: Arc::clone(&metrics),
            max_packet: config.broker.max_packet_bytes,
            max_inflight: config.broker.max_inflight,
            max_subscriptions: config.broker.max_subscriptions_per_client,
            max_sessions_per_identity: config.broker.max_sessions_per_identity,
            max_keep_alive: config.broker.max_keep_alive_s,
            connect_timeout: config.connect_timeout(),
            pending: crate::pending::Pending::new(config.broker.max_pending_per_address),
            write_timeout: Duration::from_millis(config.broker.slow_consumer_timeout_ms),
            max_queued_bytes: config.broker.slow_consumer_max_bytes,
            dead_link: config.dead_link_timeout(),
            shutdown: shutdown_rx.clone(),
            test_panic_topic: crate::supervisor::test_panic_topic("FBBUS_TEST_SESSION_PANIC_TOPIC"),
            observers,
        });

        // What the store held is back in the router before the bus or any client sees it.
        if let Some(store) = &ctx.store {
            ctx.wills.set_store(Arc::clone(store));
        }
        crate::session::restore::put_back(&restore, &ctx)
            .await
            .map_err(StartError::Router)?;
        ctx.retained_shares.restore(
            restore
                .retained_shares
                .iter()
                .map(|(share, topic, size)| (share.as_str(), topic.as_str(), *size)),
        );
        let owners = crate::session::restore::owners(&restore);
        ctx.wills.restore(&owners, restore.wills);

        #[cfg(feature = "bridge")]
        if let (Some(bridge), Some(bus)) = (&bridge, &config.bridge) {
            bridge.start(bus, Arc::clone(&ctx)).await?;
        }

        // An input topic fed from another line's device: this line asks the bus for that
        // output, as a subscriber of it would, for as long as a profile needs it.
        profiles.on_change({
            let ctx = Arc::downgrade(&ctx);
            move |before, after| {
                let Some(ctx) = ctx.upgrade() else {
                    return;
                };
                let (before, after) = (before.fed_outputs(), after.fed_outputs());
                for filter in after.difference(&before) {
                    ctx.observers.subscribed(filter);
                }
                for filter in before.difference(&after) {
                    ctx.observers.unsubscribed(filter);
                }
            }
        });

        let mut listeners = Vec::new();
        for (section, tls) in config.listeners.iter().zip(tls.drain(..)) {
            let socket = bind(&section.name, section.bind)?;
            listeners.push(Listener {
                policy: Arc::new(ListenerPolicy {
                    name: section.name.as_str().into(),
                    anonymous: section.anonymous(&config.auth),
                    transport: section.kind.transport(tls.is_some()),
                }),
                socket,
                tls,
                websocket: section.websocket().map(Arc::new),
            });
        }
        let admin_socket = bind("admin", config.admin.bind)?;
        let admin_addr = admin_socket
            .local_addr()
            .map_err(|source| StartError::Bind {
                name: "admin".into(),
                addr: config.admin.bind,
                source,
            })?;

        // Each plane its share of the process's file descriptors (`fd_budget`).
        let budget =
            crate::fd_budget::apply(config.broker.max_connections, config.admin.max_connections);
        metrics.connection_limit.set(budget.mqtt as i64);
        let slots = Arc::new(Semaphore::new(budget.mqtt));
        let bound: Vec<_> = listeners
            .iter()
            .map(|l| (l.policy.name.to_string(), l.local_addr()))
            .collect();
        for listener in listeners {
            let path = listener.websocket.as_ref().map(|w| w.path.as_str());
            tracing::info!(listener = &*listener.policy.name, addr = %listener.local_addr(),
                transport = listener.policy.transport, path, tls = listener.tls.is_some(),
                anonymous = listener.policy.anonymous, "listening (MQTT 3.1.1 and 5)");
            tasks.core(
                "listener",
                listener.run(Arc::clone(&ctx), Arc::clone(&slots)),
            );
        }

        tasks.core(
            "session expiry",
            crate::session::lifetime::expire_sessions(Arc::clone(&ctx), shutdown_rx.clone()),
        );

        // The line console: its own router link, so the packet path never waits for it.
        let console = if config.console.enabled {
            let link = ctx
                .router
                .observer_link(crate::console::activity::CLIENT_ID)
                .await
                .map_err(|e| StartError::Router(e.to_string()))?;
            Some(crate::console::Console::start(
                &config.console,
                Duration::from_millis(config.admin.connection_timeout_ms),
                config.bridge.is_some(),
                Arc::clone(&registry),
                Arc::clone(&profiles),
                Arc::clone(&ctx.wills),
                Arc::clone(&metrics),
                (link.0, link.1),
                &tasks,
            ))
        } else {
            None
        };
        let mut admin_shutdown = shutdown_rx.clone();
        tasks.core(
            "admin endpoint",
            admin::serve_apart(
                admin_socket,
                admin::Limits::from(&config.admin),
                AdminState {
                    metrics: Arc::clone(&metrics),
                    health: Arc::clone(&health),
                    registry: Arc::clone(&registry),
                    profiles: Arc::clone(&profiles),
                    auth: admin_passwords.as_ref().map(|file| {
                        Arc::new(AdminAuth::new(
                            Arc::clone(file),
                            &config.auth.throttle,
                            Arc::clone(&metrics),
                        ))
                    }),
                    console,
                    sessions: Arc::new(crate::session::control::SessionControl::new(&ctx)),
                    clients: Arc::clone(&ctx.clients),
                    retained: Arc::clone(&ctx.retained_shares),
                    writes: Arc::new(crate::admin_writes::WriteRules::new(
                        &config.admin.allowed_hosts,
                        Arc::clone(&metrics),
                    )),
                },
                async move {
                    let _ = admin_shutdown.changed().await;
                },
            ),
        );
        tracing::info!(addr = %admin_addr, credentials = admin_passwords.is_some(),
            "admin endpoint: /metrics /healthz /readyz /api/v1/devices, console at /");
        if admin_passwords.as_ref().is_some_and(|f| f.get().is_empty()) {
            tracing::warn!(
                "[admin] password_file has no user: every admin request is refused until one \
                 is added (`fbbus passwd FILE add USER`; the file is reloaded when it changes)"
            );
        }

        tasks.core(
            "file watcher",
            watch_files(
                [passwords, admin_passwords].into_iter().flatten().collect(),
                acl,
                profiles,
                Duration::from_millis(config.auth.reload_poll_ms),
                Arc::clone(&metrics),
                shutdown_rx,
            ),
        );

        health.set_started(true);
        Ok(Broker {
            listeners: bound,
            admin: admin_addr,
            metrics,
            shutdown,
            health,
            tasks,
            registry,
            store: ctx.store.clone(),
            sparkplug,
            #[cfg(feature = "bridge")]
            bridge,
        })
    }

    /// Resolves once a part the whole line depends on died (the router thread, a core
    /// task): the broker cannot serve any more and its process should exit non-zero, so
    /// the service manager restarts it. `/readyz` already fails by then.
    pub async fn died(&self) -> String {
        self.health.died().await
    }

    /// Stops everything at once, without closing connections (a core part died, see
    /// [`Broker::died`]): every task is finished, then the registry is written.
    pub async fn abort(self) {
        self.health.set_started(false);
        // Bounded: a task that does not yield cannot hold the exit up.
        let _ = tokio::time::timeout(Duration::from_secs(1), self.tasks.finish()).await;
        self.registry.flush();
        if let Some(store) = &self.store {
            store.close().await;
        }
    }

    /// Stops accepting, disconnects every client (MQTT 5: reason 0x8B, server shutting
    /// down) and waits up to `grace` for the connections to close; then closes the bus,
    /// finishes every task of the broker and writes the registry a last time. No task
    /// runs after this returns, so nothing writes the registry file concurrently with
    /// the last write.
    pub async fn shutdown(self, grace: Duration) {
        self.health.set_started(false);
        if let Some(view) = &self.sparkplug {
            view.shutdown().await;
        }
        let _ = self.shutdown.send(true);
        let deadline = tokio::time::Instant::now() + grace;
        while self.metrics.connections.get() > 0 && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        #[cfg(feature = "bridge")]
        if let Some(bridge) = &self.bridge {
            bridge.close().await;
        }
        self.tasks.finish().await;
        self.registry.flush();
        if let Some(store) = &self.store {
            store.close().await;
        }
        tracing::info!("broker stopped");
    }
}

/// Pending connections the kernel queues per listener. Linux's default for tokio's
/// `bind` is 1024: a line of 1,045 devices reconnecting at once would overflow it and
/// wait a 1 s SYN retransmit. The kernel caps it at net.core.somaxconn.
const LISTEN_BACKLOG: u32 = 4096;

fn bind(name: &str, addr: SocketAddr) -> Result<TcpListener, StartError> {
    let error = |source| StartError::Bind {
        name: name.to_owned(),
        addr,
        source,
    };
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()
    } else {
        TcpSocket::new_v6()
    }
    .map_err(error)?;
    socket.set_reuseaddr(true).map_err(error)?;
    socket.bind(addr).map_err(error)?;
    socket.listen(LISTEN_BACKLOG).map_err(error)
}

/// The files a configuration names, loaded and checked: what `fbbus check-config` verifies
/// and what `start` uses, so a file that passes the check is the file that is served.
struct Files {
    passwords: Option<Arc<WatchedFile<PasswordFile>>>,
    acl: Option<Arc<WatchedFile<AclRules>>>,
    /// `[admin] password_file`.
    admin_passwords: Option<Arc<WatchedFile<PasswordFile>>>,
    /// One entry per listener, in config order.
    tls: Vec<Option<TlsAcceptor>>,
    profiles: Arc<Profiles>,
}

impl Files {
    fn load(config: &Config) -> Result<Files, StartError> {
        let passwords = match &config.auth.password_file {
            Some(path) => Some(Arc::new(load_watched(
                "password file",
                "password_file",
                path,
                |p| PasswordFile::load(p).map_err(|e| e.to_string()),
            )?)),
            None => None,
        };
        let acl = match &config.auth.acl_file {
            Some(path) => Some(Arc::new(load_watched("ACL file", "acl_file", path, |p| {
                AclRules::load(p).map_err(|e| e.to_string())
            })?)),
            None => None,
        };
        let admin_passwords = match &config.admin.password_file {
            Some(path) => Some(Arc::new(load_watched(
                "admin password file",
                "admin_password_file",
                path,
                |p| PasswordFile::load(p).map_err(|e| e.to_string()),
            )?)),
            None => None,
        };
        let tls = config
            .listeners
            .iter()
            .map(|l| {
                l.tls
                    .as_ref()
                    .map(|tls| {
                        crate::tls::acceptor(tls).map_err(|source| StartError::Tls {
                            name: l.name.clone(),
                            source,
                        })
                    })
                    .transpose()
            })
            .collect::<Result<_, _>>()?;
        let dir = &config.fb.profiles_dir;
        let profiles = match dir.as_os_str().is_empty() {
            true => Profiles::none(),
            false => Profiles::load(dir).map_err(|message| StartError::File {
                kind: "device profiles directory",
                path: dir.display().to_string(),
                message,
            })?,
        };
        Ok(Files {
            passwords,
            acl,
            admin_passwords,
            tls,
            profiles: Arc::new(profiles),
        })
    }
}

/// Loads every file the configuration names (password file, ACL, TLS certificates and
/// keys) without binding anything: `fbbus check-config`.
pub fn check(config: &Config) -> Result<(), StartError> {
    #[cfg(feature = "bridge")]
    if let Some(bus) = &config.bridge {
        crate::bridge::Bridge::check(bus, &config.broker.line)?;
    }
    Files::load(config).map(|_| ())
}

/// `kind` names the file in errors, `label` in logs and `fbbus_file_reloads_total`.
fn load_watched<T>(
    kind: &'static str,
    label: &'static str,
    path: &std::path::Path,
    loader: impl Fn(&std::path::Path) -> Result<T, String> + Send + Sync + 'static,
) -> Result<WatchedFile<T>, StartError> {
    WatchedFile::load(label, path, loader).map_err(|message| StartError::File {
        kind,
        path: path.display().to_string(),
        message,
    })
}

/// Reloads the password files (`[auth]`'s and `[admin]`'s), the ACL file and the profiles
/// directory when they change, and at once on SIGHUP.
async fn watch_files(
    passwords: Vec<Arc<WatchedFile<PasswordFile>>>,
    acl: Option<Arc<WatchedFile<AclRules>>>,
    profiles: Arc<Profiles>,
    poll: Duration,
    metrics: Arc<Metrics>,
    mut shutdown: watch::Receiver<bool>,
) {
    // SIGHUP is always handled, so `systemctl reload` never kills a broker without files.
    let mut hangup = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()) {
        Ok(s) => Some(s),
        Err(e) => {
            tracing::warn!(error = %e, "cannot listen for SIGHUP; files reload on change only");
            None
        }
    };
    loop {
        let force = tokio::select! {
            _ = shutdown.changed() => return,
            _ = tokio::time::sleep(poll) => false,
            Some(_) = async { match hangup.as_mut() { Some(h) => h.recv().await, None => std::future::pending().await } } => {
                tracing::info!("SIGHUP: reloading password and ACL files");
                true
            }
        };
        for p in &passwords {
            p.reload(force, &metrics);
        }
        if let Some(a) = &acl {
            a.reload(force, &metrics);
        }
        profiles.reload(force, &metrics);
    }
}
