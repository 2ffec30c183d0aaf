//! One deterministic random number generator, SplitMix64 (Steele, Lea and
//! Flood 2014), with no global state: every user seeds its own, either from
//! a seed ([`SplitMix64`]) or per pixel ([`SplitMix64::for_pixel`]) so the
//! numbers a pixel draws do not depend on the order pixels run in.

/// The Weyl increment of SplitMix64 (2^64 / golden ratio).
const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// One step of SplitMix64's output function on `z + GAMMA`: a bijective
/// 64-bit mixer, also used to hash seeds together.
#[inline]
pub fn splitmix64(z: u64) -> u64 {
    let mut z = z.wrapping_add(GAMMA);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// SplitMix64: the state advances by `GAMMA`, the output is the mixed state.
#[derive(Debug, Clone)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    /// The generator of pixel `(x, y)` in `stream` for `seed`: the four
    /// numbers hashed together.
    pub fn for_pixel(seed: u64, stream: u64, x: u64, y: u64) -> Self {
        let mut h = splitmix64(seed);
        h = splitmix64(h ^ stream);
        h = splitmix64(h ^ x);
        h = splitmix64(h ^ y);
        // the per-pixel streams start one step further than a plain seed
        Self(h.wrapping_add(GAMMA))
    }

    /// Next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        let out = splitmix64(self.0);
        self.0 = self.0.wrapping_add(GAMMA);
        out
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[0, 1)` (the same as [`next_f64`](Self::next_f64)).
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        self.next_f64()
    }

    /// Uniform integer in `0..n` (`n >= 1`; `0` for `n = 0`).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.next_f64() * n as f64) as usize).min(n.saturating_sub(1))
    }

    /// Standard normal deviate (Box-Muller, one of the pair).
    #[inline]
    pub fn gaussian(&mut self) -> f64 {
        // 1 - uniform() is in (0, 1]: the guard of the logarithm.
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reference outputs of SplitMix64 seeded with 0 (from the
    /// generator's published definition), and the per-pixel stream being
    /// the plain stream of a hashed seed, one step on.
    #[test]
    fn matches_the_published_sequence() {
        let mut r = SplitMix64(0);
        assert_eq!(r.next_u64(), 0xE220_A839_7B1D_CDAF);
        assert_eq!(r.next_u64(), 0x6E78_9E6A_A1B9_65F4);
        let mut p = SplitMix64::for_pixel(1, 2, 3, 4);
        let h = splitmix64(splitmix64(splitmix64(splitmix64(1) ^ 2) ^ 3) ^ 4);
        assert_eq!(p.next_u64(), splitmix64(h.wrapping_add(GAMMA)));
        let x = SplitMix64(5).below(0);
        assert_eq!(x, 0);
    }
}
