//! Patch validation (J 3.3): Euclidean residual, coverage grid, curvature bounds; every rejection names the failed test.
