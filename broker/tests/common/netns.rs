//! Two network namespaces joined by a veth pair, for the tests that cut a link
//! (`partition.rs`, `liveness.rs`). The addresses exist only inside the namespaces; both
//! are deleted, with the pair, on drop. Processes started in them are the test's to kill
//! first.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command};
use std::sync::mpsc;

pub struct VethPair {
    /// Namespace `a`, address `<subnet>.1`, interface `veth_a`.
    pub a: String,
    /// Namespace `b`, address `<subnet>.2`, interface `veth_b`.
    pub b: String,
    pub veth_a: String,
    pub veth_b: String,
}

impl VethPair {
    /// Creates the pair: namespaces `<ns>A<pid>`/`<ns>B<pid>`, interfaces
    /// `<veth>a<pid>`/`<veth>b<pid>`, in the /24 `subnet` (e.g. "10.213.0"). An error
    /// says which `ip` step failed (no root, no namespaces), for the test to skip loudly.
    pub fn create(ns: &str, veth: &str, subnet: &str) -> Result<VethPair, String> {
        let tag = std::process::id() % 100_000;
        let pair = VethPair {
            a: format!("{ns}A{tag}"),
            b: format!("{ns}B{tag}"),
            veth_a: format!("{veth}a{tag}"),
            veth_b: format!("{veth}b{tag}"),
        };
        let (addr_a, addr_b) = (format!("{subnet}.1/24"), format!("{subnet}.2/24"));
        let (a, b, veth_a, veth_b) = (&pair.a, &pair.b, &pair.veth_a, &pair.veth_b);
        let steps: Vec<Vec<&str>> = vec![
            vec!["netns", "add", a],
            vec!["netns", "add", b],
            vec![
                "link", "add", veth_a, "type", "veth", "peer", "name", veth_b,
            ],
            vec!["link", "set", veth_a, "netns", a],
            vec!["link", "set", veth_b, "netns", b],
            vec!["-n", a, "addr", "add", &addr_a, "dev", veth_a],
            vec!["-n", b, "addr", "add", &addr_b, "dev", veth_b],
            vec!["-n", a, "link", "set", veth_a, "up"],
            vec!["-n", b, "link", "set", veth_b, "up"],
            vec!["-n", a, "link", "set", "lo", "up"],
            vec!["-n", b, "link", "set", "lo", "up"],
        ];
        for step in steps {
            let out = Command::new("ip")
                .args(&step)
                .output()
                .map_err(|e| format!("ip: {e}"))?;
            if !out.status.success() {
                return Err(format!(
                    "`ip {}` failed: {}",
                    step.join(" "),
                    String::from_utf8_lossy(&out.stderr).trim()
                ));
            }
        }
        Ok(pair)
    }

    /// `program` run inside namespace `ns`.
    pub fn exec(&self, ns: &str, program: &str) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", ns, program]);
        c
    }

    /// Sets interface `veth` of namespace `ns` up or down (down: the cable is pulled).
    pub fn set_link(&self, ns: &str, veth: &str, up: bool) {
        let status = Command::new("ip")
            .args([
                "-n",
                ns,
                "link",
                "set",
                veth,
                if up { "up" } else { "down" },
            ])
            .status()
            .expect("ip runs");
        assert!(status.success(), "ip link set {veth} in {ns}");
    }
}

impl Drop for VethPair {
    fn drop(&mut self) {
        for ns in [&self.a, &self.b] {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// Lines of a child's stdout, on a channel.
pub fn lines_of(child: &mut Child) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    let stdout = child.stdout.take().expect("stdout piped");
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                return;
            }
        }
    });
    rx
}
