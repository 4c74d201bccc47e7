//! The 10 bounded curved patch types of IROS Table I: parameters, implicit/explicit forms, boundaries, sampling, distances.
