//! Readers for recorded data: TUM RGB-D directories, directories of depth PNGs with an intrinsics JSON, single PNGs, Open3D trajectory logs.
