//! The argon2id working memory kept between verifications: never more buffers than
//! verifications ran at once, reused, and all freed on request. (Its own test binary: the
//! buffer pool is process-wide, and other tests verify passwords in parallel.)

use security::hash::{kept_verify_buffers, release_verify_buffers};
use security::{hash_password, Argon2Params, StoredHash};

#[test]
fn verification_memory_is_reused_and_released() {
    let params = Argon2Params::default();
    let stored = StoredHash::parse(&hash_password(b"right", &params).unwrap()).unwrap();
    assert_eq!(kept_verify_buffers(), 0);

    assert!(stored.verify(b"right"));
    assert!(!stored.verify(b"wrong"));
    assert_eq!(
        kept_verify_buffers(),
        1,
        "one verification at a time: one buffer"
    );

    std::thread::scope(|s| {
        for _ in 0..3 {
            s.spawn(|| assert!(stored.verify(b"right")));
        }
    });
    let kept = kept_verify_buffers();
    assert!(
        (1..=3).contains(&kept),
        "{kept} buffers after 3 parallel verifications"
    );

    release_verify_buffers();
    assert_eq!(kept_verify_buffers(), 0);
    assert!(stored.verify(b"right"), "verifies again after a release");
}
