//! ROBOTIS action files (DARwIn-OP `motion_4096.bin`, OP3 `motion_4095.bin`): 256 pages of 512 bytes,
//! each a named motion of up to 7 steps of 31 joint positions (4096 ticks per turn, 2048 = 0 rad)
//! with a move time and a pause. [`page`] reads and writes one page byte for byte ([`parse_page`]
//! takes any bytes), [`file`] the whole file, [`id_map`] says which servo ID drives which library
//! joint, [`timing`] is the players' step timing, and [`to_keyframes`] / [`to_page`] convert between
//! a page and library keyframes. ROS-free; the `step_executor import-motion` and `export-motion`
//! commands use it.
//!
//! DARwIn-OP's `motion_1024.bin` (its build for 1024-tick servos) has the same layout with positions
//! of 1024 ticks per 300°; it is not read (the commands refuse a file of that name).

pub mod file;
pub mod id_map;
pub mod page;
pub mod timing;
pub mod to_keyframes;
pub mod to_page;

pub use file::{ActionFile, ActionFileError, FILE_BYTES, PAGE_COUNT, PLAYABLE_PAGES};
pub use id_map::{IdMap, IdMapError};
pub use page::{parse_page, Page, PageError, Step, PAGE_BYTES};
pub use to_keyframes::{page_to_keyframes, ImportError, ImportedSteps};
pub use to_page::{keyframes_to_page, page_name, ExportError, ExportedPage};

#[cfg(test)]
mod tests;
