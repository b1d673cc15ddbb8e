//! Stable fingerprints of codes and matrices (sidecars, calibrations, run checks): a leaf
//! module, so the files that fingerprint and the sidecar that compares fingerprints do not
//! depend on each other.

/// FNV-1a (64 bit) of `bytes`, as 16 hex digits: a stable fingerprint (not a cryptographic hash).
pub fn digest(bytes: impl IntoIterator<Item = u8>) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    format!("{h:016x}")
}

#[cfg(test)]
mod tests {
    #[test]
    fn fnv1a_of_known_inputs() {
        // the FNV-1a 64 reference values
        assert_eq!(super::digest([]), "cbf29ce484222325");
        assert_eq!(super::digest(*b"a"), "af63dc4c8601ec8c");
    }
}
