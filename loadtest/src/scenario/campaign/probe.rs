//! The routing probe between a campaign's rounds: a fresh valid subscriber must get a
//! fresh publisher's QoS 1 message, or the broker stopped routing.

use crate::client::{self, Client, ClientConfig};
use crate::clock;
use crate::target::Target;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The routing probe: a fresh subscriber and a fresh publisher (valid clients, the
/// harness's login), one QoS 1 message on a topic with multi-byte characters, which must
/// arrive within `wait`. Returns the round trip.
pub async fn probe(
    target: &Target,
    prefix: &str,
    n: u64,
    wait: Duration,
) -> Result<Duration, String> {
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<Vec<u8>>();
    let on_publish: client::OnPublish = Arc::new(move |_topic: &[u8], payload: &[u8]| {
        let _ = tx.send(payload.to_vec());
    });
    let mut config = ClientConfig::new(format!("{prefix}-probe-sub"));
    config.timeout = wait;
    let mut sub = Client::connect(target, &config, Some(on_publish))
        .await
        .map_err(|e| format!("probe subscriber: {e}"))?;
    let filters = [
        "fbbus-loadtest/probe/#".to_owned(),
        "+/probe/+/Förderband/#".to_owned(),
    ];
    if let Err(e) = sub.subscribe(&filters, client::qos(1)).await {
        sub.abort();
        return Err(format!("probe subscriber: {e}"));
    }
    let mut config = ClientConfig::new(format!("{prefix}-probe-pub"));
    config.timeout = wait;
    let publisher = match Client::connect(target, &config, None).await {
        Ok(p) => p,
        Err(e) => {
            sub.abort();
            return Err(format!("probe publisher: {e}"));
        }
    };
    let nonce = format!("probe {n} {}", clock::now_us()).into_bytes();
    let topic = format!("fbbus-loadtest/probe/é/Förderband/{n}");
    let start = Instant::now();
    let result = match publisher
        .publish(&topic, client::qos(1), nonce.clone())
        .await
    {
        Err(e) => Err(format!("probe publisher: {e}")),
        Ok(()) => {
            let arrived = tokio::time::timeout(wait, async {
                while let Some(payload) = rx.recv().await {
                    if payload == nonce {
                        return true;
                    }
                }
                false
            })
            .await;
            match arrived {
                Ok(true) => Ok(start.elapsed()),
                Ok(false) => {
                    Err("the probe subscriber's connection ended before the probe arrived".into())
                }
                Err(_) => Err(format!(
                    "the probe message on {topic:?} did not arrive within {wait:?}"
                )),
            }
        }
    };
    publisher.disconnect().await;
    sub.disconnect().await;
    result
}
