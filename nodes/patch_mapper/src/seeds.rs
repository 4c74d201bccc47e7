//! Stage iii (J 4.3): seed selection on the gravity-aligned grid.
