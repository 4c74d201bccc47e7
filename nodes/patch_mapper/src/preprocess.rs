//! Stage ii (J 4.2): background removal, discontinuity-preserving bilateral filter, 2x2 median downsample.
