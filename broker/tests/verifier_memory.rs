//! The verification threads free argon2id's working memory once no login is queued, so an
//! idle broker keeps none of it after a storm. (Its own test binary: the buffer pool is
//! process-wide, and other tests verify passwords in parallel.)

use std::time::{Duration, Instant};

use broker::verifier::Verifier;
use security::hash::kept_verify_buffers;
use security::{hash_password, Argon2Params, StoredHash};

#[tokio::test]
async fn argon2_memory_is_freed_when_the_queue_drains() {
    let stored =
        StoredHash::parse(&hash_password(b"right", &Argon2Params::default()).unwrap()).unwrap();
    let stored = std::sync::Arc::new(stored);
    let verifier = Verifier::start(2).unwrap();

    let checks = (0..6).map(|i| {
        let stored = std::sync::Arc::clone(&stored);
        let password: &'static [u8] = if i % 2 == 0 { b"right" } else { b"wrong" };
        verifier.run(move || stored.verify(password))
    });
    let verdicts: Vec<Option<bool>> = futures_join(checks).await;
    assert_eq!(
        verdicts,
        [true, false, true, false, true, false].map(Some).to_vec()
    );

    // The last thread to finish frees the buffers just after it has answered.
    let deadline = Instant::now() + Duration::from_secs(5);
    while kept_verify_buffers() > 0 {
        assert!(
            Instant::now() < deadline,
            "{} argon2 buffers still kept 5 s after the last verification",
            kept_verify_buffers()
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Runs the futures concurrently (all queued at once) and returns their outputs in order.
async fn futures_join<F>(futures: impl Iterator<Item = F>) -> Vec<F::Output>
where
    F: std::future::Future + Send + 'static,
    F::Output: Send + 'static,
{
    let tasks: Vec<_> = futures.map(tokio::spawn).collect();
    let mut out = Vec::new();
    for task in tasks {
        out.push(task.await.unwrap());
    }
    out
}
