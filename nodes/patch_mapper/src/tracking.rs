//! Camera tracking (J 5.1): coarse-to-fine projective point-to-plane ICP with robust weights and loss detection.
