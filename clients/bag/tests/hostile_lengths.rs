//! Hostile length prefixes: a string, byte array or map whose length prefix exceeds its record
//! must be a clean error (no panic) without a huge allocation. The `mcap` crate reserves a
//! string's length before checking it, so the reader validates every record's field layout
//! first. The fuzzer's reproducers (fuzz/regressions/bag_reader/) and hand-made files.
//!
//! The test binary counts allocations: the largest single request must stay small, and so must
//! the growth of the process's peak resident memory (`VmHWM`).
use scancorr_bag::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Largest single allocation any test may make.
const LIMIT: usize = 64 << 20;

/// The system allocator, recording the largest single request, per thread (tests run in
/// parallel) and for the whole process.
struct Counting;

static LARGEST: AtomicUsize = AtomicUsize::new(0);
thread_local! {
    static THREAD_LARGEST: Cell<usize> = const { Cell::new(0) };
}

fn record(size: usize) {
    LARGEST.fetch_max(size, Ordering::Relaxed);
    // `try_with`: no panic while the thread-local is being torn down.
    let _ = THREAD_LARGEST.try_with(|m| m.set(m.get().max(size)));
}

// SAFETY: forwards every call to `System` unchanged; only records sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Peak resident memory of the process, bytes (`VmHWM` of /proc/self/status).
fn vm_hwm() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let line = status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .expect("VmHWM in /proc/self/status");
    let kb: u64 = line
        .trim_start_matches("VmHWM:")
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .expect("VmHWM in kB");
    kb * 1024
}

/// Runs `f`, asserting that neither the largest single allocation nor the peak resident memory
/// grows by `LIMIT` or more.
fn bounded<T>(what: &str, f: impl FnOnce() -> T) -> T {
    THREAD_LARGEST.with(|m| m.set(0));
    let hwm = vm_hwm();
    let out = f();
    let largest = THREAD_LARGEST.with(Cell::get);
    let grown = vm_hwm().saturating_sub(hwm);
    assert!(
        largest < LIMIT,
        "{what}: a single allocation of {largest} bytes"
    );
    assert!(
        grown < LIMIT as u64,
        "{what}: peak resident memory grew by {grown} bytes"
    );
    out
}

/// Opens `path` with and without skipping damage; the plain open must fail cleanly with an
/// error whose text contains every one of `expect`. Returns the plain open's error text.
fn open_fails(path: &Path, expect: &[&str]) -> String {
    let name = path.display().to_string();
    let err = bounded(&name, || BagReader::open(path)).expect_err("a hostile file must not open");
    let text = err.to_string();
    for e in expect {
        assert!(text.contains(e), "{name}: error {text:?} lacks {e:?}");
    }
    // Skipping damage may open the file or not, but also without a big allocation, and reading
    // what it opened must not either.
    bounded(&name, || {
        if let Ok(bag) = BagReader::open_skipping_damaged(path) {
            if let Ok(messages) = bag.messages() {
                messages.for_each(drop);
            }
        }
    });
    text
}

fn regression(name: &str) -> PathBuf {
    Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../fuzz/regressions/bag_reader/"
    ))
    .join(name)
}

#[test]
fn fuzz_header_string_4gib_is_a_clean_error() {
    let path = regression("oom-minimized-header-string-4GiB.mcap");
    let text = open_fails(
        &path,
        &[
            "damaged bag: record at byte offset 8",
            "header record: field `profile` has length prefix 4294901768",
        ],
    );
    println!("{text}");
    assert!(matches!(
        BagReader::open(&path),
        Err(BagError::Damaged { offset: 8, .. })
    ));
}

#[test]
fn fuzz_chunk_compression_string_2_6gb_is_a_clean_error() {
    let path = regression("oom-chunk-compression-string-2.6GB.mcap");
    let text = open_fails(
        &path,
        &["damaged bag: chunk", "chunk record: field `compression`"],
    );
    println!("{text}");
}

// ---- hand-made hostile files ----

const HOSTILE: u32 = u32::MAX;

fn rec(op: u8, body: &[u8]) -> Vec<u8> {
    let mut v = vec![op];
    v.extend_from_slice(&(body.len() as u64).to_le_bytes());
    v.extend_from_slice(body);
    v
}

fn string(s: &str) -> Vec<u8> {
    [(s.len() as u32).to_le_bytes().as_slice(), s.as_bytes()].concat()
}

/// A string field whose length prefix is `len` but holds `s`.
fn lying_string(len: u32, s: &str) -> Vec<u8> {
    [len.to_le_bytes().as_slice(), s.as_bytes()].concat()
}

fn map(entries: &[u8]) -> Vec<u8> {
    [(entries.len() as u32).to_le_bytes().as_slice(), entries].concat()
}

fn header() -> Vec<u8> {
    rec(0x01, &[string("scancorr"), string("hostile-test")].concat())
}

fn schema(name: Vec<u8>) -> Vec<u8> {
    let body = [
        1u16.to_le_bytes().to_vec(),
        name,
        string("protobuf"),
        (3u32).to_le_bytes().to_vec(),
        vec![1, 2, 3],
    ]
    .concat();
    rec(0x03, &body)
}

fn channel(topic: Vec<u8>, metadata: Vec<u8>) -> Vec<u8> {
    let body = [
        1u16.to_le_bytes().to_vec(),
        1u16.to_le_bytes().to_vec(),
        topic,
        string("protobuf"),
        metadata,
    ]
    .concat();
    rec(0x04, &body)
}

fn metadata(name: Vec<u8>) -> Vec<u8> {
    rec(
        0x0C,
        &[name, map(&[string("k"), string("v")].concat())].concat(),
    )
}

fn data_end() -> Vec<u8> {
    rec(0x0F, &0u32.to_le_bytes())
}

/// An uncompressed chunk holding `records` (CRC 0: not computed).
fn chunk(records: &[u8]) -> Vec<u8> {
    let body = [
        0u64.to_le_bytes().as_slice(),
        &0u64.to_le_bytes(),
        &(records.len() as u64).to_le_bytes(),
        &0u32.to_le_bytes(),
        &string(""),
        &(records.len() as u64).to_le_bytes(),
        records,
    ]
    .concat();
    rec(0x06, &body)
}

/// The whole file: magic, `data` (header first), then, when `summary` is given, the summary
/// section, and a footer (summary CRC 0) and end magic.
fn file(name: &str, data: &[Vec<u8>], summary: Option<&[Vec<u8>]>) -> PathBuf {
    let mut bytes = mcap::MAGIC.to_vec();
    for r in data {
        bytes.extend_from_slice(r);
    }
    let summary_start = match summary {
        Some(records) => {
            let start = bytes.len() as u64;
            for r in records {
                bytes.extend_from_slice(r);
            }
            start
        }
        None => 0,
    };
    let footer = [
        summary_start.to_le_bytes().as_slice(),
        &0u64.to_le_bytes(),
        &0u32.to_le_bytes(),
    ]
    .concat();
    bytes.extend_from_slice(&rec(0x02, &footer));
    bytes.extend_from_slice(mcap::MAGIC);
    let dir = std::env::temp_dir().join(format!("scancorr-bag-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, &bytes).unwrap();
    path
}

/// A statistics record (no messages, `channels` channels, no chunks, no metadata).
fn statistics() -> Vec<u8> {
    let body = [
        0u64.to_le_bytes().as_slice(),
        &1u16.to_le_bytes(),
        &1u32.to_le_bytes(),
        &0u32.to_le_bytes(),
        &0u32.to_le_bytes(),
        &0u32.to_le_bytes(),
        &0u64.to_le_bytes(),
        &0u64.to_le_bytes(),
        &map(&[]),
    ]
    .concat();
    rec(0x0B, &body)
}

#[test]
fn schema_name_of_4gib_in_the_data_section_is_a_clean_error() {
    let offset = 8 + header().len();
    let path = file(
        "schema-name.mcap",
        &[
            header(),
            schema(lying_string(HOSTILE, "scancorr.v1.ScaleBatch")),
            channel(string("cmm/m1/raw/scale"), map(&[])),
            data_end(),
        ],
        None,
    );
    let text = open_fails(
        &path,
        &[
            &format!("record at byte offset {offset}"),
            "schema record: field `name` has length prefix 4294967295",
        ],
    );
    println!("{text}");
}

#[test]
fn channel_metadata_key_of_4gib_in_a_chunk_is_a_clean_error() {
    let entries = [lying_string(HOSTILE, "k"), string("v")].concat();
    let records = [
        schema(string("scancorr.v1.ScaleBatch")),
        channel(string("cmm/m1/raw/scale"), map(&entries)),
    ]
    .concat();
    let offset = 8 + header().len();
    let path = file(
        "channel-metadata-key.mcap",
        &[header(), chunk(&records), data_end()],
        None,
    );
    let text = open_fails(
        &path,
        &[
            &format!("chunk at byte offset {offset}"),
            "channel record: field `metadata` entry 0 key has length prefix 4294967295",
        ],
    );
    println!("{text}");
}

#[test]
fn channel_map_and_metadata_name_of_4gib_are_clean_errors() {
    // The map's own byte length exceeds the record.
    let path = file(
        "channel-map-length.mcap",
        &[
            header(),
            schema(string("scancorr.v1.ScaleBatch")),
            channel(
                string("cmm/m1/raw/scale"),
                lying_string(HOSTILE, "\u{1}\0\0\0k"),
            ),
            data_end(),
        ],
        None,
    );
    open_fails(
        &path,
        &["channel record: field `metadata` has length prefix 4294967295"],
    );

    // A complete file whose summary has a hostile channel topic and whose data section has a
    // hostile metadata name: the summary is not used, the scan fails on the metadata record.
    let path = file(
        "summary-channel-topic.mcap",
        &[header(), metadata(lying_string(HOSTILE, "run")), data_end()],
        Some(&[
            schema(string("scancorr.v1.ScaleBatch")),
            channel(lying_string(HOSTILE, "cmm/m1/raw/scale"), map(&[])),
            statistics(),
        ]),
    );
    open_fails(
        &path,
        &["metadata record: field `name` has length prefix 4294967295"],
    );
}

#[test]
fn hostile_summary_record_is_not_used() {
    // The data section is intact: the summary is unusable and noted, the scan reads the file.
    let path = file(
        "summary-only.mcap",
        &[
            header(),
            schema(string("scancorr.v1.ScaleBatch")),
            channel(string("cmm/m1/raw/scale"), map(&[])),
            data_end(),
        ],
        Some(&[
            schema(lying_string(HOSTILE, "scancorr.v1.ScaleBatch")),
            channel(string("cmm/m1/raw/scale"), map(&[])),
            statistics(),
        ]),
    );
    let bag = bounded("summary-only", || BagReader::open(&path)).expect("the scan reads it");
    let notes = bag.damage_notes().join("\n");
    assert!(
        notes.contains("schema record: field `name` has length prefix 4294967295"),
        "{notes}"
    );
    assert_eq!(bag.channels().len(), 1);
}
