//! Stage ii (J 4.2.1): hiking saliency - integral-image normals, DoN, DoNG and distance-to-fixation-point filters.
