//! `scancorr proto`: the wire contract's FileDescriptorSet written to a file.

use crate::shared::output;
use anyhow::Result;
use std::path::PathBuf;

/// Runs `scancorr proto`.
pub fn exec(out: PathBuf) -> Result<()> {
    output::write_file("--out", &out, scancorr_proto::FILE_DESCRIPTOR_SET)?;
    eprintln!(
        "{}: FileDescriptorSet of package {} ({} bytes)",
        out.display(),
        scancorr_proto::PACKAGE,
        scancorr_proto::FILE_DESCRIPTOR_SET.len()
    );
    Ok(())
}
