//! `patch_mapper track` (placeholder until its issue lands).

/// Arguments of `patch_mapper track`.
#[derive(clap::Args, Debug)]
pub struct TrackArgs {}

pub fn run(_args: TrackArgs) -> anyhow::Result<()> {
    anyhow::bail!("`track` is not available yet")
}
