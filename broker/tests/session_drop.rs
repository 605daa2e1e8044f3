//! Issue 33, "no lockout": a kept session of one identity cannot block another identity's
//! client id forever. A client id that is a user's name is that user's (issue 33, tested
//! in `fair_shares.rs`); for every other client id, an operator sees who holds it
//! (`fbbus sessions`, `GET /api/v1/sessions`) and drops a kept session
//! (`fbbus sessions drop ID`, `DELETE /api/v1/sessions/ID`), after which the device
//! connects again. A connected session is not dropped.

mod common;

use std::process::Command;
use std::time::Duration;

use common::clients::V4;
use common::{add_user, fbbus_bin, http_get, run, Broker, Options};

const OWNED: &str = "fbbus_connects_refused_total{reason=\"client_id_owned\"}";

/// A line whose conveyor devices share the user `conveyor` (their client ids are not
/// usernames, so no client id is reserved), and a user `devA`.
fn line() -> Broker {
    Broker::start_with(
        Options {
            extra: "[auth]\npassword_file = \"passwd\"\n".into(),
            ..Default::default()
        },
        |dir| {
            add_user(&dir.join("passwd"), "conveyor", "pw-conveyor");
            add_user(&dir.join("passwd"), "devA", "pw-devA");
        },
    )
}

fn fbbus(broker: &Broker, args: &[&str]) -> (bool, String, String) {
    let admin = broker.admin.to_string();
    let mut cmd = Command::new(fbbus_bin());
    cmd.args(args).args(["--admin", &admin]);
    run(&mut cmd, Duration::from_secs(30))
}

/// The sequence: devA parks a 3.1.1 session (clean session 0, never expires)
/// on conveyor device conv-3's client id while conv-3 is away; conv-3 is refused; the
/// operator lists and drops the session; conv-3 connects, and the drop is counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_frees_a_client_id_another_user_parked_a_session_on() {
    let broker = line();
    let port = broker.port();
    let mut squat = V4::options(port, "conv-3", Some(("devA", "pw-devA")));
    squat.set_clean_session(false);
    let squatter = V4::connect_with(squat)
        .await
        .expect("devA connects as conv-3");
    // Connected: not dropped.
    let (ok, _, err) = fbbus(&broker, &["sessions", "drop", "conv-3"]);
    assert!(!ok);
    assert!(err.contains("is connected"), "{err}");
    squatter.client.disconnect().await.unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while sessions(&broker)["sessions"][0]["status"] != "kept" {
        assert!(
            std::time::Instant::now() < deadline,
            "{}",
            sessions(&broker)
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    drop(squatter);

    // Kept offline and owned by devA: the real conv-3 is locked out.
    let conv3 = || {
        let mut o = V4::options(port, "conv-3", Some(("conveyor", "pw-conveyor")));
        o.set_clean_session(false);
        V4::connect_with(o)
    };
    let refused = broker.metric(OWNED);
    assert!(conv3().await.is_err(), "conv-3 was let in");
    assert_eq!(broker.metric(OWNED), refused + 1.0);

    // The operator sees who holds it...
    let (ok, out, err) = fbbus(&broker, &["sessions"]);
    assert!(ok, "{err}");
    let row = out
        .lines()
        .find(|l| l.starts_with("conv-3 "))
        .unwrap_or_else(|| panic!("no conv-3 row\n{out}"));
    assert!(
        row.contains("devA") && row.contains("kept") && row.ends_with("never"),
        "{out}"
    );
    let page = sessions(&broker);
    assert_eq!(page["total"], 1, "{page}");
    assert_eq!(page["sessions"][0]["owner"], "devA", "{page}");

    // ...and drops it: conv-3 is back.
    let (ok, out, err) = fbbus(&broker, &["sessions", "drop", "conv-3"]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("dropped"), "{out}");
    assert_eq!(broker.metric("fbbus_sessions_dropped_total"), 1.0);
    assert!(broker
        .log_text()
        .contains("kept session dropped by an operator"));
    let real = conv3()
        .await
        .unwrap_or_else(|e| panic!("conv-3 still refused: {e}\n{}", broker.log_text()));
    assert_eq!(broker.metric(OWNED), refused + 1.0);

    // Unknown and connected client ids: named, nothing dropped.
    let (ok, _, err) = fbbus(&broker, &["sessions", "drop", "nobody"]);
    assert!(!ok && err.contains("no session with client id"), "{err}");
    let (ok, _, err) = fbbus(&broker, &["sessions", "drop", "conv-3"]);
    assert!(!ok && err.contains("is connected"), "{err}");
    assert_eq!(broker.metric("fbbus_sessions_dropped_total"), 1.0);
    drop(real);
}

/// `GET /api/v1/sessions`.
fn sessions(broker: &Broker) -> serde_json::Value {
    let (status, body) = http_get(broker.admin, "/api/v1/sessions").unwrap();
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}
