//! Whether this machine's CPU has the instructions the binary was compiled for.
//!
//! The workspace compiles for the CPU of the machine that builds it (`.cargo/config.toml`:
//! `target-cpu=native`, e.g. AVX2, FMA, AVX-512 on x86-64). A binary copied to a machine whose CPU
//! lacks some of them would stop at the first such instruction with "Illegal instruction", possibly
//! in the middle of a motion. [`missing_features`] compares the features the compiler was allowed to
//! use with those the CPU reports, so the nodes refuse to start with a message that says what to do.
//! The check is itself compiled for the build machine: it catches the common case (a build for a
//! newer CPU of the same family, e.g. AVX-512 run on AVX2), not a CPU without any of them.

/// Those of the listed target features that were enabled at compile time and that `std::arch::$detect`
/// does not find on this CPU.
macro_rules! missing_among {
    ($detect:ident; $($feature:tt),* $(,)?) => {{
        let mut missing = Vec::new();
        $(
            if cfg!(target_feature = $feature) && !std::arch::$detect!($feature) {
                missing.push($feature);
            }
        )*
        missing
    }};
}

/// The target features enabled at compile time that this CPU does not report.
#[cfg(target_arch = "x86_64")]
pub fn missing_features() -> Vec<&'static str> {
    missing_among!(is_x86_feature_detected;
        "sse3", "ssse3", "sse4.1", "sse4.2", "popcnt", "avx", "avx2", "fma", "f16c", "bmi1", "bmi2", "lzcnt", "movbe", "avx512f",
        "avx512cd", "avx512bw", "avx512dq", "avx512vl", "avx512vnni", "avx512vbmi", "avx512vbmi2", "avx512bitalg", "avx512vpopcntdq",
        "avx512ifma", "avx512bf16", "avx512fp16", "avxvnni", "gfni", "vaes", "vpclmulqdq",
    )
}

/// The target features enabled at compile time that this CPU does not report.
#[cfg(target_arch = "aarch64")]
pub fn missing_features() -> Vec<&'static str> {
    missing_among!(is_aarch64_feature_detected;
        "neon", "fp16", "dotprod", "i8mm", "bf16", "sve", "sve2", "lse", "rcpc", "crc", "aes", "sha2")
}

/// Other architectures: nothing known to check.
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
pub fn missing_features() -> Vec<&'static str> {
    Vec::new()
}

/// `Err` with a message for a person when [`missing_features`] is not empty.
pub fn check() -> Result<(), String> {
    refusal(&missing_features()).map_or(Ok(()), Err)
}

/// What a node says when the CPU lacks `missing` (`None` when nothing is missing).
fn refusal(missing: &[&str]) -> Option<String> {
    (!missing.is_empty()).then(|| {
        format!(
            "this binary was compiled for a CPU with {} which this machine's CPU does not have (it was built on another \
             machine; the workspace compiles for the CPU that builds it): build it on this machine, or on the other one \
             with RUSTFLAGS=\"-C target-cpu=<this machine's CPU>\"",
            missing.join(", ")
        )
    })
}

#[cfg(test)]
mod tests {
    /// The tests run on the machine that built them: nothing the compiler used is missing.
    #[test]
    fn the_building_machine_has_every_feature_it_compiled_for() {
        assert_eq!(super::missing_features(), Vec::<&str>::new());
        assert!(super::check().is_ok());
    }

    /// A refusal names every missing feature and how to build for this machine.
    #[test]
    fn a_refusal_names_what_is_missing_and_the_remedy() {
        assert_eq!(super::refusal(&[]), None);
        let text = super::refusal(&["avx512f", "avx512bw"]).unwrap();
        assert!(text.contains("avx512f, avx512bw"), "{text}");
        assert!(text.contains("build it on this machine") && text.contains("RUSTFLAGS"), "{text}");
    }
}
