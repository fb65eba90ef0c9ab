//! A damaged bag is never read silently: `scancorr correct` of a bag with one byte changed
//! inside a chunk fails naming the chunk, where before it wrote changed points.

mod common;
use common::*;

#[test]
fn correct_refuses_a_bag_whose_chunk_checksum_fails() {
    let d = scratch("damaged-bag");
    sim_ring(&d, "c.json");
    ok(
        &d,
        &[
            "correct",
            "--bag",
            "r.mcap",
            "--calib",
            "c.json",
            "--out",
            "good.mcap",
        ],
    );
    let bytes = std::fs::read(d.join("r.mcap")).unwrap();
    // One bit changed in the middle of the file (inside the chunks that hold the messages).
    let mut bad = bytes.clone();
    bad[bytes.len() / 2] ^= 0x10;
    std::fs::write(d.join("bad.mcap"), &bad).unwrap();
    let err = fails(
        &d,
        &[
            "correct", "--bag", "bad.mcap", "--calib", "c.json", "--out", "o.mcap",
        ],
        &["bad.mcap", "damaged"],
    );
    assert!(
        !d.join("o.mcap").exists(),
        "no output from a damaged bag:\n{err}"
    );
}
