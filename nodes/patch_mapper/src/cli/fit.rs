//! `patch_mapper fit` (placeholder until its issue lands).

/// Arguments of `patch_mapper fit`.
#[derive(clap::Args, Debug)]
pub struct FitArgs {}

pub fn run(_args: FitArgs) -> anyhow::Result<()> {
    anyhow::bail!("`fit` is not available yet")
}
