//! `step_executor import-motion`: one page of a ROBOTIS action file added to the motion library as a
//! new motion, its target patch taken from a motion already trained.

use std::path::PathBuf;

use anyhow::Context;
use step_executor::action_file::{page_to_keyframes, ActionFile};
use step_executor::library::Motion;

use super::motion_files::{refuse_1024_tick_file, LibraryArgs};

#[derive(clap::Args, Debug, Clone)]
pub struct ImportMotionArgs {
    /// ROBOTIS action file: DARwIn-OP's motion_4096.bin or OP3's motion_4095.bin (256 pages of 512 bytes).
    #[arg(value_name = "ACTION_FILE")]
    pub action_file: PathBuf,
    /// Page to import (1..=255); it must be a time-based page with 1..=7 steps and a valid checksum.
    #[arg(long)]
    pub page: u16,
    /// Name of the new library motion (must not exist yet).
    #[arg(long)]
    pub name: String,
    /// Library motion whose trained target patch the new motion takes (every library motion is
    /// matched against its patch, and an action page has none).
    #[arg(long, value_name = "MOTION")]
    pub target_from: String,
    #[command(flatten)]
    pub files: LibraryArgs,
}

pub fn run(args: ImportMotionArgs) -> anyhow::Result<()> {
    refuse_1024_tick_file(&args.action_file)?;
    let bytes = std::fs::read(&args.action_file).with_context(|| format!("cannot read {}", args.action_file.display()))?;
    let source = args.action_file.display();
    let file = ActionFile::from_bytes(bytes).with_context(|| source.to_string())?;
    let page = file.page(args.page).with_context(|| source.to_string())?;
    let mut files = args.files.load()?;
    let imported = page_to_keyframes(&page, &files.map, &files.limits).with_context(|| format!("{source} page {}", args.page))?;
    let target = files.library.get(&args.target_from).with_context(|| {
        format!("no motion named {:?} to take the target patch from (the library has {:?})", args.target_from, files.library.names())
    })?;
    let motion = Motion { name: args.name.clone(), patch: target.patch.clone(), keyframes: imported.keyframes };
    let keyframes = motion.keyframes.len();
    let duration: f64 = motion.keyframes.iter().map(|k| k.move_s + k.pause_s).sum();
    files.library.insert(motion)?;
    files.library.save()?;
    println!(
        "imported page {} {:?} of {source} as motion {:?} in {}: {keyframes} keyframes, {duration:.3} s, play speed {}, target of {:?}",
        args.page,
        page.name_text(),
        args.name,
        files.library.path().display(),
        page.speed,
        args.target_from
    );
    if !imported.unmapped_ids.is_empty() {
        println!("ignored the positions of IDs without a library joint: {:?}", imported.unmapped_ids);
    }
    Ok(())
}
