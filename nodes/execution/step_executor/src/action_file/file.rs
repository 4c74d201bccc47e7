//! A whole action file (`motion_4096.bin`, `motion_4095.bin`): 256 pages of 512 bytes, page `n` at
//! byte `512 n`. Page 0 is not played by ROBOTIS' players; pages 1–255 hold motions.

use super::page::{parse_page, Page, PageError, PAGE_BYTES};

/// Pages in an action file.
pub const PAGE_COUNT: usize = 256;
/// Bytes of an action file.
pub const FILE_BYTES: usize = PAGE_COUNT * PAGE_BYTES;
/// The pages that hold motions.
pub const PLAYABLE_PAGES: std::ops::RangeInclusive<u16> = 1..=255;

/// Why a file or a page of it cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ActionFileError {
    #[error("not an action file: it is {0} bytes, an action file is {FILE_BYTES} (256 pages of {PAGE_BYTES} bytes)")]
    Length(usize),
    #[error("page {0} is out of range: motions are on pages 1..=255 (page 0 is never played)")]
    PageOutOfRange(u16),
    #[error("page {page}: {source}")]
    Page { page: u16, source: PageError },
}

/// The bytes of an action file, checked for length only: a page is parsed when it is asked for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ActionFile {
    bytes: Vec<u8>,
}

impl ActionFile {
    /// A file of 256 empty pages ([`Page::empty`]).
    pub fn new_empty() -> Self {
        let page = Page::empty().to_bytes();
        Self { bytes: page.iter().copied().cycle().take(FILE_BYTES).collect() }
    }

    /// The file's bytes; any length other than [`FILE_BYTES`] is refused.
    pub fn from_bytes(bytes: Vec<u8>) -> Result<Self, ActionFileError> {
        if bytes.len() != FILE_BYTES {
            return Err(ActionFileError::Length(bytes.len()));
        }
        Ok(Self { bytes })
    }

    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// The raw 512 bytes of page `page` (1..=255).
    pub fn page_bytes(&self, page: u16) -> Result<&[u8], ActionFileError> {
        let at = page_offset(page)?;
        Ok(&self.bytes[at..at + PAGE_BYTES])
    }

    /// Page `page` parsed (checksum and step count checked).
    pub fn page(&self, page: u16) -> Result<Page, ActionFileError> {
        parse_page(self.page_bytes(page)?).map_err(|source| ActionFileError::Page { page, source })
    }

    /// Replace page `page` with `content` (its checksum is computed).
    pub fn set_page(&mut self, page: u16, content: &Page) -> Result<(), ActionFileError> {
        let at = page_offset(page)?;
        self.bytes[at..at + PAGE_BYTES].copy_from_slice(&content.to_bytes());
        Ok(())
    }
}

fn page_offset(page: u16) -> Result<usize, ActionFileError> {
    if !PLAYABLE_PAGES.contains(&page) {
        return Err(ActionFileError::PageOutOfRange(page));
    }
    Ok(usize::from(page) * PAGE_BYTES)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_file_has_256_valid_empty_pages() {
        let file = ActionFile::new_empty();
        assert_eq!(file.as_bytes().len(), 131_072);
        for page in PLAYABLE_PAGES {
            assert_eq!(file.page(page).unwrap(), Page::empty());
        }
    }

    #[test]
    fn wrong_length_and_page_numbers_are_refused() {
        assert_eq!(ActionFile::from_bytes(vec![0; 1000]).unwrap_err(), ActionFileError::Length(1000));
        let file = ActionFile::new_empty();
        assert_eq!(file.page(0).unwrap_err(), ActionFileError::PageOutOfRange(0));
        assert_eq!(file.page(256).unwrap_err(), ActionFileError::PageOutOfRange(256));
        assert!(file.page(0).unwrap_err().to_string().contains("1..=255"));
    }

    #[test]
    fn set_page_replaces_only_that_page() {
        let mut file = ActionFile::new_empty();
        let before = file.clone();
        let mut page = Page::empty();
        page.step_count = 1;
        page.name[..4].copy_from_slice(b"walk");
        file.set_page(9, &page).unwrap();
        assert_eq!(file.page(9).unwrap(), page);
        assert_eq!(file.page_bytes(8).unwrap(), before.page_bytes(8).unwrap());
        assert_eq!(file.page_bytes(10).unwrap(), before.page_bytes(10).unwrap());
    }

    #[test]
    fn a_corrupt_page_is_named() {
        let mut bytes = ActionFile::new_empty().as_bytes().to_vec();
        bytes[3 * PAGE_BYTES + 100] ^= 0x01;
        let file = ActionFile::from_bytes(bytes).unwrap();
        let err = file.page(3).unwrap_err();
        assert!(matches!(err, ActionFileError::Page { page: 3, source: PageError::Checksum { .. } }), "{err}");
        file.page(4).unwrap();
    }
}
