//! Patch tracking (J 5.2 steps 1-9): move patches with volume remaps, drop those outside, re-associate cells.
