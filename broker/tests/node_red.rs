//! Issue 35: Node-RED's own MQTT nodes (npm `node-red`, run headless from a flow file)
//! over MQTT over WebSockets (`ws://.../mqtt`, MQTT 5), exchanging typed values with a
//! device on the line. Node-RED declares its interface with its broker node's birth
//! message, as a device declares at connect; it reads a device's INT and publishes one of
//! its own, once ill-typed (refused, on diag, never delivered) and once well-typed.

mod common;

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::fb::*;
use common::{free_port, Broker, Options};
use serde_json::json;

/// Node-RED's start script, from the npm package `.ci/run` installs.
fn node_red() -> Option<PathBuf> {
    common::require("node").then_some(())?;
    common::npm_file("node-red/red.js")
}

/// Node-RED as a child process, killed when dropped; its output in `log`.
struct NodeRed {
    child: Child,
    log: PathBuf,
}

impl NodeRed {
    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for NodeRed {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

const NODE_RED_DECLARATION: &str =
    r#"{"fbs":{"SCALE":{"data_in":{"IN":"INT"},"data_out":{"OUT":"INT"}}}}"#;

/// The flow (ids in Node-RED's own form: a node property equal to another node's id is
/// read as a reference, so a name like an id makes a "circular dependency"): a broker node for `ws://127.0.0.1:<ws_port>/mqtt` (client id `nr-1`, MQTT 5,
/// the declaration as its birth message), `mqtt in` on plc-1's SPEED, a function that
/// doubles it and first sends an ill-typed value, `mqtt out`.
fn flow(ws_port: u16) -> serde_json::Value {
    json!([
        {"id": "b0a1c2d3e4f50000", "type": "tab", "label": "fbbus"},
        {
            "id": "b0a1c2d3e4f50001", "type": "mqtt-broker", "name": "fbbus",
            "broker": format!("ws://127.0.0.1:{ws_port}/mqtt"), "port": "",
            "clientid": "nr-1", "autoConnect": true, "usetls": false,
            "protocolVersion": "5", "keepalive": "60", "cleansession": true,
            "autoUnsubscribe": true,
            "birthTopic": "fbbus/declare/nr-1", "birthQos": "1", "birthRetain": "false",
            "birthPayload": NODE_RED_DECLARATION, "birthMsg": {},
            "closeTopic": "", "willTopic": ""
        },
        {
            "id": "b0a1c2d3e4f50002", "type": "mqtt in", "z": "b0a1c2d3e4f50000", "topic": "fb/plc-1/CONV/POSITION",
            "qos": "1", "datatype": "utf8", "broker": "b0a1c2d3e4f50001", "nl": false, "rap": true,
            "rh": 0, "inputs": 0, "wires": [["b0a1c2d3e4f50003"]]
        },
        {
            "id": "b0a1c2d3e4f50003", "type": "function", "z": "b0a1c2d3e4f50000", "name": "double",
            "func": "const v = Number(msg.payload);\n\
                     return [[{topic: 'fb/nr-1/SCALE/OUT', payload: 'not a number'},\n\
                              {topic: 'fb/nr-1/SCALE/OUT', payload: String(v * 2)}]];",
            "outputs": 1, "wires": [["b0a1c2d3e4f50004"]]
        },
        {
            "id": "b0a1c2d3e4f50004", "type": "mqtt out", "z": "b0a1c2d3e4f50000", "topic": "", "qos": "1",
            "retain": "false", "broker": "b0a1c2d3e4f50001", "wires": []
        }
    ])
}

/// Headless: no editor, no HTTP nodes, no telemetry; nothing listens, nothing leaves
/// loopback.
const SETTINGS: &str = r#"module.exports = {
    flowFile: "flows.json",
    credentialSecret: false,
    uiHost: "127.0.0.1",
    httpAdminRoot: false,
    httpNodeRoot: false,
    diagnostics: { enabled: false, ui: false },
    telemetry: { enabled: false, updateNotification: false },
    logging: { console: { level: "info", metrics: false, audit: false } },
    externalModules: { autoInstall: false, palette: { allowInstall: false } }
};
"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn node_reds_mqtt_nodes_exchange_typed_values_over_websockets() {
    let Some(red) = node_red() else { return };
    let ws_port = free_port();
    let broker = Broker::start_with(
        Options {
            extra: format!(
                "[[listener]]\nname = \"web\"\nkind = \"ws\"\nbind = \"127.0.0.1:{ws_port}\"\n"
            ),
            ..Default::default()
        },
        |_| {},
    );
    let mut watch = observer(
        &broker,
        "watch",
        &["fbbus/diag/plc-1", "fbbus/diag/nr-1", "fb/nr-1/#"],
    )
    .await;
    let mut plc = Dev::connect(broker.port(), 5, "plc-1");
    declare_ok(&mut plc, CONV, &mut watch, &broker).await;

    let user_dir = broker.dir.path().join("node-red");
    std::fs::create_dir_all(&user_dir).unwrap();
    std::fs::write(user_dir.join("settings.js"), SETTINGS).unwrap();
    std::fs::write(user_dir.join("flows.json"), flow(ws_port).to_string()).unwrap();
    let log = user_dir.join("node-red.log");
    let red = NodeRed {
        child: Command::new("node")
            .arg(&red)
            .args(["--userDir", user_dir.to_str().unwrap()])
            .args(["--settings", user_dir.join("settings.js").to_str().unwrap()])
            .current_dir(&user_dir)
            .env("NO_PROXY", "127.0.0.1,localhost")
            .stdout(std::fs::File::create(&log).unwrap())
            .stderr(Stdio::null())
            .spawn()
            .expect("node runs Node-RED"),
        log,
    };
    let why = |what: &str| {
        format!(
            "{what}\n--- Node-RED\n{}\n--- broker\n{}",
            red.log_text(),
            broker.log_text()
        )
    };

    // Its birth message declares it.
    let answer = wait_diag(&mut watch, "nr-1", Duration::from_secs(60))
        .await
        .unwrap_or_else(|| panic!("{}", why("Node-RED never declared nr-1")));
    assert_eq!(
        answer["kind"],
        "declaration",
        "{}",
        why(&answer.to_string())
    );
    assert_eq!(answer["ok"], true, "{}", why(&answer.to_string()));
    // Its subscription is in place once the broker counts one on the web listener's
    // connection; a moment for the SUBSCRIBE after the birth message.
    let deadline = Instant::now() + Duration::from_secs(20);
    while !red.log_text().contains("Connected to broker") && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;

    assert_eq!(plc.publish("fb/plc-1/CONV/POSITION", b"21"), 0);
    // The ill-typed value is refused (diag), the doubled one delivered, typed.
    let mut refused = None;
    let mut delivered = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    while (refused.is_none() || delivered.is_empty()) && Instant::now() < deadline {
        let Some((topic, payload)) = next_under(&mut watch, "", Duration::from_secs(1)).await
        else {
            continue;
        };
        let text = String::from_utf8_lossy(&payload).into_owned();
        match topic.as_str() {
            "fbbus/diag/nr-1" => refused = Some(text),
            "fb/nr-1/SCALE/OUT" => delivered.push(text),
            _ => {}
        }
    }
    let refused = refused.unwrap_or_else(|| panic!("{}", why("no refusal on diag")));
    let refused: serde_json::Value = serde_json::from_str(&refused).unwrap();
    assert_eq!(refused["kind"], "rejected", "{refused}");
    assert_eq!(refused["reason"], "payload_format_invalid", "{refused}");
    assert_eq!(refused["topic"], "fb/nr-1/SCALE/OUT", "{refused}");
    assert_eq!(delivered, vec!["42".to_owned()], "{}", why("delivered"));
    let rest = drain(&mut watch, QUIET).await;
    assert!(
        rest.iter().all(|(t, _)| t != "fb/nr-1/SCALE/OUT"),
        "{rest:?}"
    );
    let record = broker_record(&broker, "nr-1");
    assert_eq!(record["status"], "online", "{record}");
    assert_eq!(
        record["interface"]["fbs"]["SCALE"]["data_out"]["OUT"], "INT",
        "{record}"
    );
    drop(red);
}

/// The next message on `fbbus/diag/<device>` within `limit`, parsed.
async fn wait_diag(
    watch: &mut common::clients::V4,
    device: &str,
    limit: Duration,
) -> Option<serde_json::Value> {
    let topic = format!("fbbus/diag/{device}");
    let deadline = Instant::now() + limit;
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        let (t, payload) = next_under(watch, "fbbus/diag/", left).await?;
        if t == topic {
            return serde_json::from_slice(&payload).ok();
        }
    }
    None
}

/// The device's registry record from the admin API.
fn broker_record(broker: &Broker, id: &str) -> serde_json::Value {
    let (status, body) = common::http_get(broker.admin, &format!("/api/v1/devices/{id}"))
        .expect("the admin endpoint answers");
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}
