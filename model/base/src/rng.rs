//! A small deterministic PRNG (SplitMix64): synthetic scenes, benchmarks and tests are
//! reproducible from a seed without an extra crate.

#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }
    /// The generator's whole state (to save in a checkpoint).
    pub fn state(&self) -> u64 {
        self.0
    }
    /// A generator that goes on from `state` (from [`state`](Self::state)).
    pub fn from_state(state: u64) -> Self {
        Self(state)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn f(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f()
    }
    /// An index drawn with probability proportional to `weights` (non-negative, not all zero;
    /// the last index when rounding runs past the end).
    pub fn weighted(&mut self, weights: &[f32]) -> usize {
        let mut u = self.f() * weights.iter().sum::<f32>();
        for (i, w) in weights.iter().enumerate() {
            if u < *w {
                return i;
            }
            u -= w;
        }
        weights.len().saturating_sub(1)
    }
    /// Shuffles `v` in place (Fisher-Yates from the back: every permutation equally likely).
    pub fn shuffle<T>(&mut self, v: &mut [T]) {
        for i in (1..v.len()).rev() {
            let j = (self.next_u64() % (i as u64 + 1)) as usize;
            v.swap(i, j);
        }
    }
    /// Moves a uniform random choice of `k` of `v`'s items, in random order, to its front
    /// (Fisher-Yates from the front, stopped after `k` draws; `k` clamped to the length).
    pub fn partial_shuffle<T>(&mut self, v: &mut [T], k: usize) {
        let n = v.len();
        for i in 0..k.min(n) {
            let j = i + (self.next_u64() % (n - i) as u64) as usize;
            v.swap(i, j);
        }
    }
    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f32 {
        let u1 = self.f().max(1e-7);
        let u2 = self.f();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::Rng;

    #[test]
    fn shuffles_are_seeded_permutations() {
        let mut a: Vec<usize> = (0..50).collect();
        Rng::new(7).shuffle(&mut a);
        let mut b: Vec<usize> = (0..50).collect();
        Rng::new(7).shuffle(&mut b);
        assert_eq!(a, b, "the same seed, the same order");
        assert_ne!(a, (0..50).collect::<Vec<_>>(), "shuffled");
        let mut sorted = a.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..50).collect::<Vec<_>>(), "a permutation");

        let mut p: Vec<usize> = (0..10).collect();
        Rng::new(3).partial_shuffle(&mut p, 4);
        let mut sorted = p.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..10).collect::<Vec<_>>(), "still a permutation");
        let mut q: Vec<usize> = (0..3).collect();
        Rng::new(3).partial_shuffle(&mut q, 99);
        q.sort_unstable();
        assert_eq!(q, [0, 1, 2], "k past the length is clamped");
    }
}
