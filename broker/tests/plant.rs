//! Issue 32: a plant, not a pair. Five lines on one bus: lines 1 and 2 are zenoh routers
//! (`mode = "router"`) linked to each other, lines 3 to 5 are zenoh clients of both, as a
//! plant with two redundant routers runs them (here the routers are fbbus lines, as the
//! issue's own attempt did; `zenohd` itself is not installed in CI). Each line has
//! `DEVICES` declared devices.
//!
//! - every line lists every device of the bus online (and says how long it took);
//! - a device of line 3 reaches a subscriber of line 5, every message once and in order;
//! - router line 1 is SIGKILLed: after the lease, lines 3 to 5 still list each other's
//!   devices online (their clients moved to router line 2), and line 3 -> line 5 goes on,
//!   every message once and in order.

//!
//! And the plant of `deploy/plant/`, as `make-plant.sh` writes it: five lines, zenoh
//! clients over mutual TLS of two zenoh routers linked to each other. The routers run the
//! generated `router-*.json5` in Python `eclipse-zenoh` 1.10, the zenoh library of
//! `zenohd` 1.10 (CI cannot build zenohd; `deploy/plant/check.sh` runs the real one).
//! Either router killed in turn: every line lists every device online again within the
//! lease, and a stream of messages across the failovers arrives once each, in order.
//!
//! And the link between the two routers cut and healed ([`Cable`]), with two real zenoh
//! routers (Python's zenoh): lines that are peers of each other and of both routers lose
//! nothing; lines that are zenoh clients of different routers are split until the link
//! heals (a zenoh client session has one router at a time), then whole again; lines with
//! a session per router (`[bridge] session_per_router`) are not split by the cut, nor by
//! either router killed in turn, and a line started while a router is down takes its
//! session there when the router comes. The cut is also made by the kernel
//! ([`RouterNets`]: each router in a network namespace, their link a veth pair set down;
//! skipped, with the reason, where namespaces cannot be made). What a cut loses is
//! counted on both sides: by the line that missed it and by the line that sent it.

mod common;

use std::net::SocketAddr;
use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::bus::*;
use common::clients::V4;
use common::{fbbus_bin, free_port, Broker};

const DEVICES: usize = 20;
const LINES: usize = 5;

fn id(line: usize, device: usize) -> String {
    format!("l{line}-dev-{device:02}")
}

/// Waits until `line` lists `want` devices online; returns how long it took.
async fn converged(line: &Line, want: usize, within: Duration) -> Duration {
    let started = Instant::now();
    loop {
        let online = line
            .broker
            .metric("fbbus_registry_devices{status=\"online\"}");
        if online >= want as f64 {
            return started.elapsed();
        }
        assert!(
            started.elapsed() < within,
            "line {} lists {online} of {want} devices online\n{}",
            line.name,
            line.broker.log_text()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Publishes `range` from `dev` and checks `sub` gets each once, in order.
async fn once_in_order(dev: &V4, sub: &mut V4, topic: &str, range: std::ops::RangeInclusive<i64>) {
    for i in range.clone() {
        publish(dev, topic, i.to_string(), false).await;
    }
    let mut got = Vec::new();
    let deadline = Instant::now() + PROPAGATION;
    while got.len() < range.clone().count() && Instant::now() < deadline {
        if let Some(p) = sub.next_publish(Duration::from_millis(200)).await {
            got.push(p);
        }
    }
    got.extend(drain(sub, Duration::from_millis(500)).await);
    let want: Vec<i64> = range.collect();
    assert_eq!(positions(&got, topic), want, "once each, in order");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn five_lines_two_routers_converge_and_survive_a_router() {
    let (r1, r2) = (tcp_endpoint(), tcp_endpoint());
    let router = "mode = \"router\"\n";
    let client = "mode = \"client\"\n";
    let mut lines = vec![
        Line::start_on("line-1", &r1, &[], router, None),
        Line::start_on("line-2", &r2, &[&r1], router, None),
    ];
    for n in 3..=LINES {
        lines.push(Line::start_on(
            &format!("line-{n}"),
            "",
            &[&r1, &r2],
            client,
            None,
        ));
    }
    let mut devices = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        for d in 0..DEVICES {
            devices.push(device(line, &id(n + 1, d)).await);
        }
    }
    let everyone = LINES * DEVICES;
    let mut slowest = Duration::ZERO;
    for line in &lines {
        slowest = slowest.max(converged(line, everyone, Duration::from_secs(30)).await);
    }
    eprintln!("every line listed all {everyone} devices online within {slowest:?} of the last declaration");

    let topic = format!("fb/{}/CONV/POSITION", id(3, 0));
    let mut sub = V4::connect(lines[4].port(), "hmi-5", None).await.unwrap();
    sub.subscribe(&topic).await;
    // The interest reaches line 3 through a router.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let publisher = &devices[2 * DEVICES];
    once_in_order(publisher, &mut sub, &topic, 1..=20).await;

    lines[0].broker.kill_now();
    let killed = Instant::now();
    // Line 1's devices go unreachable; every other line's devices are online again (or
    // still) once the clients of line 1 moved to router line 2: within the lease and
    // zenoh's reconnection.
    for line in &lines[2..] {
        line.wait_record(&id(1, 0), "unreachable", PROPAGATION);
    }
    for line in &lines[1..] {
        for n in 2..=LINES {
            for d in [0, DEVICES - 1] {
                if line.name != format!("line-{n}") {
                    // On failure every line's log: the one that did not come back tells
                    // why (once in a full parallel run, line 4 of line 2, after 10 s).
                    if let Err(failure) = line.poll_record(&id(n, d), "online", PROPAGATION) {
                        let logs: String = lines[1..]
                            .iter()
                            .map(|l| format!("\n--- {}\n{}", l.name, l.broker.log_text()))
                            .collect();
                        panic!("{failure}{logs}");
                    }
                }
            }
        }
    }
    eprintln!(
        "after router line 1 died, every other line listed the others online again within {:?}",
        killed.elapsed()
    );
    once_in_order(publisher, &mut sub, &topic, 21..=40).await;
    drop(devices);
}

/// A router of the generated plant (`router-1`, `router-2`) in Python's zenoh.
fn zenoh_router(dir: &Path, name: &str) -> Python {
    let tls = dir.join("tls");
    let file = |f: &Path| f.to_str().unwrap().to_owned();
    let (config, ca) = (
        file(&dir.join(format!("{name}.json5"))),
        file(&tls.join("bus-ca.crt")),
    );
    let (cert, key) = (file(&tls.join("line-1.crt")), file(&tls.join("line-1.key")));
    // The last four arguments serve the script's "stranger" command, not used here.
    let router = Python::spawn(
        "zenoh_router.py",
        &[&config, "tls/127.0.0.1:1", &ca, &cert, &key],
    );
    assert_eq!(
        router.next_line(Duration::from_secs(20)).as_deref(),
        Some("ready"),
        "{name} did not start"
    );
    router
}

/// Four declared devices on each line, all listed online everywhere, and a subscriber on
/// the last line to the first device's topic (returned), its interest given a second to
/// reach the first line.
async fn four_devices_and_an_hmi(lines: &[Line]) -> (Vec<V4>, V4, String) {
    let mut devices = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        for d in 0..4 {
            devices.push(device(line, &id(n + 1, d)).await);
        }
    }
    let everyone = lines.len() * 4;
    let took = all_online(lines, everyone, Duration::from_secs(30)).await;
    eprintln!("every line listed all {everyone} devices online after {took:?}");
    let topic = format!("fb/{}/CONV/POSITION", id(1, 0));
    let mut sub = V4::connect(lines[lines.len() - 1].port(), "hmi", None)
        .await
        .unwrap();
    sub.subscribe(&topic).await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    (devices, sub, topic)
}

/// How long until every line lists `want` devices online, all at once.
async fn all_online(lines: &[Line], want: usize, within: Duration) -> Duration {
    let started = Instant::now();
    loop {
        let lows: Vec<f64> = lines
            .iter()
            .map(|l| l.broker.metric("fbbus_registry_devices{status=\"online\"}"))
            .collect();
        if lows.iter().all(|n| *n >= want as f64) {
            return started.elapsed();
        }
        assert!(
            started.elapsed() < within,
            "lines list {lows:?} devices online, not {want}, after {within:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_deploy_plant_survives_either_router() {
    if !python_zenoh() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (port_1, port_2) = (free_port(), free_port());
    let script = format!(
        "{}/../deploy/plant/make-plant.sh",
        env!("CARGO_MANIFEST_DIR")
    );
    let (ok, out, err) = common::run(
        Command::new("bash")
            .args([
                &script,
                &LINES.to_string(),
                dir.path().to_str().unwrap(),
                fbbus_bin(),
            ])
            .env("ROUTER_1_PORT", port_1.to_string())
            .env("ROUTER_2_PORT", port_2.to_string()),
        Duration::from_secs(60),
    );
    assert!(ok, "make-plant.sh: {out}{err}");
    let mut router_1 = Some(zenoh_router(dir.path(), "router-1"));
    let mut router_2 = Some(zenoh_router(dir.path(), "router-2"));

    // The lines as generated, their MQTT and admin ports moved to free ones.
    let mut lines = Vec::new();
    for k in 1..=LINES {
        let (mqtt, admin) = (free_port(), free_port());
        let text = std::fs::read_to_string(dir.path().join(format!("line-{k}.toml")))
            .unwrap()
            .replace(
                &format!("127.0.0.1:{}\"", 1882 + k),
                &format!("127.0.0.1:{mqtt}\""),
            )
            .replace(
                &format!("127.0.0.1:{}\"", 9882 + k),
                &format!("127.0.0.1:{admin}\""),
            );
        let line_dir = tempfile::tempdir_in(dir.path()).unwrap();
        let config = line_dir.path().join("fbbus.toml");
        std::fs::write(&config, text).unwrap();
        lines.push(Line {
            broker: Broker::spawn(
                line_dir,
                config,
                format!("127.0.0.1:{mqtt}").parse().unwrap(),
                format!("127.0.0.1:{admin}").parse().unwrap(),
            ),
            name: format!("line-{k}"),
            zenoh: String::new(),
        });
    }
    let (devices, mut sub, topic) = four_devices_and_an_hmi(&lines).await;
    let everyone = LINES * 4;
    let publisher = &devices[0];
    once_in_order(publisher, &mut sub, &topic, 1..=20).await;

    // The lease is 3 s; a failover of a client line takes zenoh about a second. CI's
    // machine may be slower: 2 s of slack.
    let within = Duration::from_secs(5);
    drop(router_1.take());
    tokio::time::sleep(Duration::from_millis(200)).await;
    let took = all_online(&lines, everyone, within).await;
    eprintln!("router-1 killed: every line listed every device online again after {took:?}");
    once_in_order(publisher, &mut sub, &topic, 21..=40).await;

    router_1 = Some(zenoh_router(dir.path(), "router-1"));
    // router-2 links to router-1 again (it retries), then router-2 dies.
    tokio::time::sleep(Duration::from_secs(2)).await;
    drop(router_2.take());
    tokio::time::sleep(Duration::from_millis(200)).await;
    let took = all_online(&lines, everyone, within).await;
    eprintln!("router-2 killed: every line listed every device online again after {took:?}");
    once_in_order(publisher, &mut sub, &topic, 41..=60).await;
    drop((devices, router_1));
}

/// The cable between the two routers: a loopback relay the test can cut. Cut, it is a
/// pulled cable: bytes vanish both ways and nothing is closed, so each router notices only
/// when its lease runs out, as on a plant. A connection that saw the cut is closed once
/// the cable is back (its peer gave it up meanwhile), and the routers connect again.
struct Cable {
    port: u16,
    cut: Arc<AtomicBool>,
}

impl Cable {
    /// A cable from a port of its own to `to` on 127.0.0.1.
    async fn lay(to: u16) -> Cable {
        Cable::lay_to(SocketAddr::from(([127, 0, 0, 1], to))).await
    }

    /// A cable from a port of its own on 127.0.0.1 to `to`.
    async fn lay_to(to: SocketAddr) -> Cable {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let cut = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&cut);
        tokio::spawn(async move {
            while let Ok((near, _)) = listener.accept().await {
                let cut = Arc::clone(&flag);
                tokio::spawn(async move {
                    let Ok(far) = tokio::net::TcpStream::connect(to).await else {
                        return;
                    };
                    let ((near_rx, near_tx), (far_rx, far_tx)) =
                        (near.into_split(), far.into_split());
                    tokio::join!(
                        carry(near_rx, far_tx, Arc::clone(&cut)),
                        carry(far_rx, near_tx, cut)
                    );
                });
            }
        });
        Cable { port, cut }
    }

    fn endpoint(&self) -> String {
        format!("tcp/127.0.0.1:{}", self.port)
    }

    fn set_cut(&self, cut: bool) {
        self.cut.store(cut, Ordering::SeqCst);
    }
}

/// What links a [`CutPlant`]'s two routers, for the test to cut.
enum RouterLink {
    /// A [`Cable`] on loopback.
    Relay(Cable),
    /// A veth pair between the routers' namespaces ([`RouterNets`]); the relays carry
    /// the lines to the routers and are never cut.
    Veth {
        // Held for the lines, and dropped before `net`: nothing left connected into
        // namespaces being deleted.
        _relays: [Cable; 2],
        net: RouterNets,
    },
}

impl RouterLink {
    fn set_cut(&self, cut: bool) {
        match self {
            RouterLink::Relay(cable) => cable.set_cut(cut),
            RouterLink::Veth { net, .. } => net.pair.set_link(&net.pair.a, &net.pair.veth_a, !cut),
        }
    }
}

/// The port both routers listen on inside their namespaces.
const ROUTER_PORT: u16 = 7447;

/// Two network namespaces, one per router, joined by a veth pair (the routers' cable,
/// 10.216.0.0/24), and a veth pair from the test's namespace to each (10.217.0.0/24 and
/// 10.218.0.0/24) for the lines' relays. The second router cannot reach the first but by
/// the cable: its namespace has no route to the first's other address. All of it goes
/// with the namespaces on drop.
struct RouterNets {
    pair: common::netns::VethPair,
}

impl RouterNets {
    const CABLE_1: &'static str = "10.216.0.1";
    const HOST_1: &'static str = "10.217.0.2";
    const HOST_2: &'static str = "10.218.0.2";

    fn create() -> Result<RouterNets, String> {
        let pair = common::netns::VethPair::create("fbr", "vr", "10.216.0")?;
        let tag = std::process::id() % 100_000;
        for (n, ns, subnet) in [(1, &pair.a, "10.217.0"), (2, &pair.b, "10.218.0")] {
            let (host, far) = (format!("vh{n}{tag}"), format!("vn{n}{tag}"));
            let (host_ip, far_ip) = (format!("{subnet}.1/24"), format!("{subnet}.2/24"));
            let steps: [&[&str]; 6] = [
                &["link", "add", &host, "type", "veth", "peer", "name", &far],
                &["link", "set", &far, "netns", ns],
                &["addr", "add", &host_ip, "dev", &host],
                &["link", "set", &host, "up"],
                &["-n", ns, "addr", "add", &far_ip, "dev", &far],
                &["-n", ns, "link", "set", &far, "up"],
            ];
            for step in steps {
                let out = Command::new("ip").args(step).output();
                match out {
                    Ok(out) if out.status.success() => {}
                    Ok(out) => {
                        return Err(format!(
                            "`ip {}` failed: {}",
                            step.join(" "),
                            String::from_utf8_lossy(&out.stderr).trim()
                        ))
                    }
                    Err(e) => return Err(format!("ip: {e}")),
                }
            }
        }
        Ok(RouterNets { pair })
    }
}

/// One direction of the cable (bounded: it ends with either socket, or after a cut).
async fn carry(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    cut: Arc<AtomicBool>,
) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut buf = vec![0u8; 64 * 1024];
    let mut saw_cut = false;
    loop {
        // Woken at least every 100 ms, so a cable healed under an idle link closes it.
        let n = match tokio::time::timeout(Duration::from_millis(100), from.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return,
            Ok(Ok(n)) => n,
            Err(_) => 0,
        };
        if cut.load(Ordering::SeqCst) {
            saw_cut = true;
            continue;
        }
        if saw_cut || (n > 0 && to.write_all(&buf[..n]).await.is_err()) {
            return;
        }
    }
}

/// A plain zenoh router in Python's zenoh (the zenoh of zenohd 1.10), listening on
/// `listen`, linking to `connect`, with the lines' lease.
fn plain_router(dir: &Path, name: &str, listen: &str, connect: &[String]) -> Python {
    plain_router_in(None, dir, name, &[listen], connect)
}

/// [`plain_router`] in network namespace `netns`, listening on every one of `listen`.
fn plain_router_in(
    netns: Option<&str>,
    dir: &Path,
    name: &str,
    listen: &[&str],
    connect: &[String],
) -> Python {
    let config = dir.join(format!("{name}.json5"));
    let text = serde_json::json!({
        "mode": "router",
        "listen": {"endpoints": listen},
        "connect": {"endpoints": connect},
        "scouting": {"multicast": {"enabled": false}},
        "transport": {"link": {"tx": {"lease": 3000}}},
    });
    std::fs::write(&config, text.to_string()).unwrap();
    // The last four arguments serve the script's "stranger" command, not used here.
    let router = Python::spawn_in(
        netns,
        "zenoh_router.py",
        &[config.to_str().unwrap(), "tcp/127.0.0.1:1", "-", "-", "-"],
    );
    assert_eq!(
        router.next_line(Duration::from_secs(20)).as_deref(),
        Some("ready"),
        "{name} did not start"
    );
    router
}

/// How many devices each line lists as `status`.
fn listed(lines: &[Line], status: &str) -> Vec<f64> {
    let series = format!("fbbus_registry_devices{{status=\"{status}\"}}");
    lines.iter().map(|l| l.broker.metric(&series)).collect()
}

/// Five lines on two zenoh routers linked by a [`Cable`]; `bridge(n)` is line n's
/// `[bridge]` (mode and endpoints). Each line has 4 devices, all online everywhere before
/// this returns; also a subscriber on line 5 to line 1's first device.
struct CutPlant {
    dir: tempfile::TempDir,
    /// Router 1's endpoint (router 2 reaches it through the cable).
    router_1: String,
    routers: Vec<Python>,
    cable: RouterLink,
    lines: Vec<Line>,
    devices: Vec<V4>,
    sub: V4,
    topic: String,
}

impl CutPlant {
    async fn start(
        attach: impl Fn(usize, &str, &str) -> (String, Vec<String>, String),
    ) -> CutPlant {
        let dir = tempfile::tempdir().unwrap();
        let (port_1, port_2) = (free_port(), free_port());
        let (r1, r2) = (
            format!("tcp/127.0.0.1:{port_1}"),
            format!("tcp/127.0.0.1:{port_2}"),
        );
        let cable = Cable::lay(port_1).await;
        let routers = vec![
            plain_router(dir.path(), "router-1", &r1, &[]),
            plain_router(dir.path(), "router-2", &r2, &[cable.endpoint()]),
        ];
        CutPlant::around(dir, (r1, r2), routers, RouterLink::Relay(cable), attach).await
    }

    /// The same plant with each router in a network namespace of its own, the two
    /// namespaces linked by a veth pair, the cable [`RouterLink::Veth`] pulls. The lines
    /// reach the routers through loopback relays that are never cut (a line's bus
    /// endpoint off loopback would have to be mutual TLS).
    async fn start_in_namespaces(
        attach: impl Fn(usize, &str, &str) -> (String, Vec<String>, String),
    ) -> Result<CutPlant, String> {
        let net = RouterNets::create()?;
        let dir = tempfile::tempdir().unwrap();
        let at = |ip: &str| format!("tcp/{ip}:{ROUTER_PORT}");
        let routers = vec![
            plain_router_in(
                Some(&net.pair.a),
                dir.path(),
                "router-1",
                &[&at(RouterNets::CABLE_1), &at(RouterNets::HOST_1)],
                &[],
            ),
            plain_router_in(
                Some(&net.pair.b),
                dir.path(),
                "router-2",
                &[&at(RouterNets::HOST_2)],
                &[at(RouterNets::CABLE_1)],
            ),
        ];
        let to = |ip: &str| SocketAddr::new(ip.parse().unwrap(), ROUTER_PORT);
        let relays = [
            Cable::lay_to(to(RouterNets::HOST_1)).await,
            Cable::lay_to(to(RouterNets::HOST_2)).await,
        ];
        let (r1, r2) = (relays[0].endpoint(), relays[1].endpoint());
        let link = RouterLink::Veth {
            _relays: relays,
            net,
        };
        Ok(CutPlant::around(dir, (r1, r2), routers, link, attach).await)
    }

    /// The lines and devices of a plant whose routers are up, reached at `r1` and `r2`.
    async fn around(
        dir: tempfile::TempDir,
        (r1, r2): (String, String),
        routers: Vec<Python>,
        cable: RouterLink,
        attach: impl Fn(usize, &str, &str) -> (String, Vec<String>, String),
    ) -> CutPlant {
        let mut lines = Vec::new();
        for n in 1..=LINES {
            let (listen, connect, bridge) = attach(n, &r1, &r2);
            let connect: Vec<&str> = connect.iter().map(String::as_str).collect();
            lines.push(Line::start_on(
                &format!("line-{n}"),
                &listen,
                &connect,
                &bridge,
                None,
            ));
        }
        let (devices, sub, topic) = four_devices_and_an_hmi(&lines).await;
        let mut plant = CutPlant {
            dir,
            router_1: r1,
            routers,
            cable,
            lines,
            devices,
            sub,
            topic,
        };
        plant.stream(1..=20).await;
        plant
    }

    /// Every line lists every device of the plant online, now.
    fn everyone_online(&self, when: &str) {
        let everyone = (LINES * 4) as f64;
        assert_eq!(
            listed(&self.lines, "online"),
            vec![everyone; LINES],
            "{when}"
        );
    }

    /// Line 1's device publishes `range`; line 5's subscriber gets each once, in order.
    async fn stream(&mut self, range: std::ops::RangeInclusive<i64>) {
        once_in_order(&self.devices[0], &mut self.sub, &self.topic, range).await;
    }
}

/// Longer than the lease (3 s) and zenoh's reconnection: what a cut has done by then, it
/// does for as long as it lasts.
const CUT_SETTLES: Duration = Duration::from_secs(5);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lines_that_are_peers_of_both_routers_lose_nothing_when_the_routers_link_is_cut() {
    if !python_zenoh() {
        return;
    }
    // Each line a peer that listens and connects to both routers: zenoh links the lines
    // to each other as well (gossip), and routes each message once.
    let mut plant = CutPlant::start(|_, r1, r2| {
        let routers = vec![r1.to_owned(), r2.to_owned()];
        (tcp_endpoint(), routers, "mode = \"peer\"\n".into())
    })
    .await;
    plant.cable.set_cut(true);
    // Every 100 ms for longer than the lease: no line ever lists a device otherwise.
    let cut = Instant::now();
    while cut.elapsed() < CUT_SETTLES {
        plant.everyone_online("while cut");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(listed(&plant.lines, "unreachable"), vec![0.0; LINES]);
    plant.stream(21..=40).await;
    plant.cable.set_cut(false);
    tokio::time::sleep(CUT_SETTLES).await;
    plant.everyone_online("healed");
    plant.stream(41..=60).await;
    // The routers only introduced the lines to each other: both may go.
    plant.routers.clear();
    tokio::time::sleep(CUT_SETTLES).await;
    plant.everyone_online("no router");
    plant.stream(61..=80).await;
    for line in &plant.lines {
        let dropped = line
            .broker
            .metric("fbbus_bridge_dropped_total{reason=\"duplicate\"}");
        assert_eq!(
            dropped, 0.0,
            "{}: zenoh delivered a message twice",
            line.name
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lines_that_are_clients_of_different_routers_are_split_by_a_cut_and_whole_when_it_heals() {
    if !python_zenoh() {
        return;
    }
    // Lines 1-3 prefer router 1, lines 4-5 router 2: a zenoh client is on one router
    // at a time, the first of its list that answers.
    let mut plant = CutPlant::start(|n, r1, r2| {
        let order = if n <= 3 { [r1, r2] } else { [r2, r1] };
        let routers = order.map(str::to_owned).to_vec();
        (String::new(), routers, "mode = \"client\"\n".into())
    })
    .await;
    plant.cable.set_cut(true);
    // The documented limit (docs/device-contract.md, "What the federation guarantees"):
    // the lines of router 1 see those of router 2 unreachable, and the other way round.
    let cut = Instant::now();
    while listed(&plant.lines, "online") != [12.0, 12.0, 12.0, 8.0, 8.0] {
        assert!(
            cut.elapsed() < 2 * CUT_SETTLES,
            "not split: {:?} online",
            listed(&plant.lines, "online")
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(
        listed(&plant.lines, "unreachable"),
        vec![8.0, 8.0, 8.0, 12.0, 12.0],
        "while cut"
    );
    // Line 2, on line 1's side of the cut, takes line 1's stream meanwhile: line 1 goes
    // on numbering it, and line 5 misses those 20.
    let mut near = V4::connect(plant.lines[1].port(), "hmi-2", None)
        .await
        .unwrap();
    near.subscribe(&plant.topic).await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    once_in_order(&plant.devices[0], &mut near, &plant.topic, 21..=40).await;
    plant.cable.set_cut(false);
    let healed = Instant::now();
    all_online(&plant.lines, LINES * 4, Duration::from_secs(15)).await;
    eprintln!(
        "the cable healed: every line listed every device online again after {:?}",
        healed.elapsed()
    );
    plant.stream(41..=60).await;
    // What line 5 missed is counted on both sides: by line 5, and by line 1 from line 5's
    // report.
    const LOST: &str = "fbbus_bridge_lost_total";
    const REPORTED: &str = "fbbus_bridge_lost_reported_total";
    assert_eq!(
        plant.lines[4].broker.metric(LOST),
        20.0,
        "line 5 missed 21-40"
    );
    let lost_elsewhere: f64 = plant.lines[..4].iter().map(|l| l.broker.metric(LOST)).sum();
    assert_eq!(lost_elsewhere, 0.0, "line 2 took 21-40");
    let deadline = Instant::now() + Duration::from_secs(5);
    while plant.lines[0].broker.metric(REPORTED) < 20.0 {
        assert!(
            Instant::now() < deadline,
            "line 1 was never told: {}",
            plant.lines[0].broker.metric(REPORTED)
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert_eq!(plant.lines[0].broker.metric(REPORTED), 20.0, "counted once");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lines_with_a_session_per_router_are_not_split_by_a_cut_nor_by_a_router_killed() {
    if !python_zenoh() {
        return;
    }
    // As in the test above, lines 1-3 list router 1 first and lines 4-5 router 2; but each
    // line is a client of both at once, one zenoh session per router.
    let mut plant = CutPlant::start(|n, r1, r2| {
        let order = if n <= 3 { [r1, r2] } else { [r2, r1] };
        let routers = order.map(str::to_owned).to_vec();
        let bridge = "mode = \"client\"\nsession_per_router = true\n";
        (String::new(), routers, bridge.into())
    })
    .await;
    let duplicates = |plant: &CutPlant| -> f64 {
        let series = "fbbus_bridge_dropped_total{reason=\"duplicate\"}";
        plant.lines.iter().map(|l| l.broker.metric(series)).sum()
    };
    // Linked routers: line 5 gets each message of line 1 through both, and drops a copy.
    assert!(
        duplicates(&plant) > 0.0,
        "no copy came through the second router: are there two sessions?"
    );
    plant.cable.set_cut(true);
    // Every 100 ms for longer than the lease: no line ever lists a device otherwise.
    let cut = Instant::now();
    while cut.elapsed() < CUT_SETTLES {
        plant.everyone_online("while cut");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    plant.stream(21..=40).await;
    plant.cable.set_cut(false);
    tokio::time::sleep(CUT_SETTLES).await;
    plant.everyone_online("healed");
    plant.stream(41..=60).await;
    let sessions_up = |plant: &CutPlant| -> Vec<f64> {
        let series = "fbbus_bridge_router_sessions_up";
        plant
            .lines
            .iter()
            .map(|l| l.broker.metric(series))
            .collect()
    };
    assert_eq!(sessions_up(&plant), vec![2.0; LINES]);
    // Router 1 killed: lines 1-3 put through their session on router 2 from then on.
    plant.routers.remove(0);
    let killed = Instant::now();
    while killed.elapsed() < CUT_SETTLES {
        plant.everyone_online("router 1 killed");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(sessions_up(&plant), vec![1.0; LINES], "router 1 killed");
    plant.stream(61..=80).await;
    // Router 1 back on its port: each line's session on router 1 returns to it (a zenoh
    // client waits for its own router), so router 2 may go next without a dip.
    let router_1 = plain_router(plant.dir.path(), "router-1", &plant.router_1, &[]);
    plant.routers.insert(0, router_1);
    let back = Instant::now();
    while sessions_up(&plant) != vec![2.0; LINES] {
        assert!(
            back.elapsed() < 3 * CUT_SETTLES,
            "sessions back on router 1: {:?}",
            sessions_up(&plant)
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!(
        "every line on both routers again {:?} after router 1 returned",
        back.elapsed()
    );
    plant.routers.remove(1);
    let killed = Instant::now();
    while killed.elapsed() < CUT_SETTLES {
        plant.everyone_online("router 1 returned, router 2 killed");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    plant.stream(81..=100).await;
    for line in &plant.lines {
        let late = line
            .broker
            .metric("fbbus_bridge_dropped_total{reason=\"late\"}");
        eprintln!("{}: {late} late copies dropped", line.name);
    }
}

/// The same cut as above, made by the kernel: each router in a network namespace of its
/// own, the link between them a veth pair set down and up again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lines_with_a_session_per_router_stay_whole_when_the_routers_veth_is_pulled() {
    if !python_zenoh() {
        return;
    }
    let started = CutPlant::start_in_namespaces(|n, r1, r2| {
        let order = if n <= 3 { [r1, r2] } else { [r2, r1] };
        let routers = order.map(str::to_owned).to_vec();
        let bridge = "mode = \"client\"\nsession_per_router = true\n";
        (String::new(), routers, bridge.into())
    })
    .await;
    let mut plant = match started {
        Ok(plant) => plant,
        Err(e) => {
            return eprintln!("SKIPPED: cannot create network namespaces here: {e}");
        }
    };
    // Line 5 gets line 1's stream through both routers (line 1 puts through router 1;
    // router 1 sends it to line 5's session there and to router 2 for line 5's session
    // there) and drops one copy of each: so the copies tell whether the cable carries.
    let copies = |plant: &CutPlant| {
        let series = "fbbus_bridge_dropped_total{reason=\"duplicate\"}";
        plant.lines[LINES - 1].broker.metric(series)
    };
    assert!(
        copies(&plant) > 0.0,
        "no copy came through the second router"
    );
    plant.cable.set_cut(true);
    let cut = Instant::now();
    while cut.elapsed() < CUT_SETTLES {
        plant.everyone_online("while the veth is down");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(listed(&plant.lines, "unreachable"), vec![0.0; LINES]);
    let before = copies(&plant);
    plant.stream(21..=40).await;
    assert_eq!(copies(&plant), before, "a copy crossed the pulled veth");
    plant.cable.set_cut(false);
    tokio::time::sleep(CUT_SETTLES).await;
    plant.everyone_online("veth up again");
    plant.stream(41..=60).await;
    assert!(copies(&plant) > before, "the routers never linked again");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_line_started_while_a_router_is_down_takes_its_session_there_once_it_comes() {
    if !python_zenoh() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (r1, r2) = (
        format!("tcp/127.0.0.1:{}", free_port()),
        format!("tcp/127.0.0.1:{}", free_port()),
    );
    // Router 2 is down while the lines start: each line is up on router 1 alone.
    let mut routers = vec![plain_router(dir.path(), "router-1", &r1, &[])];
    let bridge = "mode = \"client\"\nsession_per_router = true\n";
    let lines: Vec<Line> = (1..=3)
        .map(|n| Line::start_on(&format!("line-{n}"), "", &[&r1, &r2], bridge, None))
        .collect();
    let (devices, mut sub, topic) = four_devices_and_an_hmi(&lines).await;
    once_in_order(&devices[0], &mut sub, &topic, 1..=10).await;
    let gauge = |name: &str| -> Vec<f64> { lines.iter().map(|l| l.broker.metric(name)).collect() };
    assert_eq!(gauge("fbbus_bridge_router_sessions"), vec![2.0; 3]);
    assert_eq!(gauge("fbbus_bridge_router_sessions_up"), vec![1.0; 3]);

    // Router 2 comes: each line's second session opens and is given what the line
    // declared meanwhile (its token, its records, line 3's interest in line 1's topic).
    routers.push(plain_router(
        dir.path(),
        "router-2",
        &r2,
        std::slice::from_ref(&r1),
    ));
    let came = Instant::now();
    while gauge("fbbus_bridge_router_sessions_up") != vec![2.0; 3] {
        assert!(
            came.elapsed() < 3 * CUT_SETTLES,
            "sessions on router 2: {:?}",
            gauge("fbbus_bridge_router_sessions_up")
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // Router 1 killed: everything now goes through the sessions opened late.
    routers.remove(0);
    let killed = Instant::now();
    while killed.elapsed() < CUT_SETTLES {
        assert_eq!(
            listed(&lines, "online"),
            vec![12.0; 3],
            "router 1 killed, {:?} after",
            killed.elapsed()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    once_in_order(&devices[0], &mut sub, &topic, 11..=20).await;
}
