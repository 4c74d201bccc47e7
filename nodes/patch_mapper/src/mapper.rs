//! The single-frame patch mapper: stages i-v as one straight pipeline with one config.
