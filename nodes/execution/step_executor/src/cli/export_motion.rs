//! `step_executor export-motion`: a library motion written as one page of a ROBOTIS action file, into
//! an existing file (only that page changes) or a new file of 256 pages.

use std::path::PathBuf;

use anyhow::Context;
use step_executor::action_file::{keyframes_to_page, page_name, ActionFile, ActionFileError, Page, PageError};
use step_executor::library::{write_atomically, LibraryError};

use super::motion_files::{refuse_1024_tick_file, LibraryArgs};

#[derive(clap::Args, Debug, Clone)]
pub struct ExportMotionArgs {
    /// Library motion to export (at most 7 keyframes: a page holds 7 steps).
    #[arg(long)]
    pub name: String,
    /// Action file to write: an existing one keeps every other page; a missing one is created with
    /// 256 pages (the others empty).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Page to write (1..=255).
    #[arg(long)]
    pub page: u16,
    /// Name stored in the page (at most 13 printable ASCII characters) [default: the name of the
    /// page replaced, else the motion's name].
    #[arg(long, value_name = "TEXT")]
    pub page_name: Option<String>,
    /// Overwrite a page that already holds steps (or has a bad checksum).
    #[arg(long)]
    pub replace: bool,
    #[command(flatten)]
    pub files: LibraryArgs,
}

pub fn run(args: ExportMotionArgs) -> anyhow::Result<()> {
    refuse_1024_tick_file(&args.out)?;
    let out = args.out.display();
    let files = args.files.load()?;
    let motion = files.library.get(&args.name).ok_or_else(|| LibraryError::NotFound(args.name.clone()))?;
    let (mut file, existing) = match std::fs::read(&args.out) {
        Ok(bytes) => (ActionFile::from_bytes(bytes).with_context(|| out.to_string())?, true),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => (ActionFile::new_empty(), false),
        Err(e) => return Err(e).with_context(|| format!("cannot read {out}")),
    };
    let template = match file.page(args.page) {
        Ok(page) if page.step_count > 0 && !args.replace => anyhow::bail!(
            "{out} page {} already holds {:?} with {} steps; pass --replace to overwrite it",
            args.page,
            page.name_text(),
            page.step_count
        ),
        Ok(page) => page,
        Err(ActionFileError::Page { source: PageError::Checksum { .. }, .. }) if args.replace => Page::empty(),
        Err(e) => {
            return Err(e).with_context(|| format!("{out}{}", if existing { " (pass --replace to overwrite a corrupt page)" } else { "" }))
        }
    };
    let name = match &args.page_name {
        Some(text) => page_name(text)?,
        None if template.step_count > 0 => template.name,
        None => page_name(&motion.name).context("the motion's name cannot be a page name; give one with --page-name")?,
    };
    let exported = keyframes_to_page(&motion.keyframes, &files.map, &files.limits, &template, name)
        .with_context(|| format!("motion {:?}", motion.name))?;
    file.set_page(args.page, &exported.page)?;
    write_atomically(&args.out, file.as_bytes()).with_context(|| format!("cannot write {out}"))?;
    println!(
        "wrote motion {:?} to page {} {:?} of {out}{}: {} steps at play speed {}, timing within {:.1} ms",
        motion.name,
        args.page,
        exported.page.name_text(),
        if existing { "" } else { " (new file)" },
        exported.page.step_count,
        exported.page.speed,
        exported.max_timing_error_s * 1000.0
    );
    Ok(())
}
