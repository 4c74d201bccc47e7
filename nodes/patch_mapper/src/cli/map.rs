//! `patch_mapper map` (placeholder until its issue lands).

/// Arguments of `patch_mapper map`.
#[derive(clap::Args, Debug)]
pub struct MapArgs {}

pub fn run(_args: MapArgs) -> anyhow::Result<()> {
    anyhow::bail!("`map` is not available yet")
}
