//! [`MemorySource`]: samples held in memory as tensors, served as a [`BatchSource`] with a
//! seeded per-epoch order. Tests, the built-in toy task ([`super::toy`]) and small experiments
//! use it; [`epoch_order`] is the shuffling any source can share.

use tch::{Kind, Tensor};

use super::{Batch, BatchSource};
use crate::error::{Error, Result};

/// SplitMix64 (Steele et al. 2014): a tiny, well-mixed, seedable generator. Deterministic on
/// every platform, which is all the data order needs.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)` (53 bits).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `0..n` (n > 0; the modulo bias is below 2^-40 for the sizes used here).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

/// The order of `n` samples in `epoch` for `seed`: a Fisher-Yates shuffle driven by
/// [`SplitMix64`] seeded from `(seed, epoch)`. The same inputs always give the same order.
pub fn epoch_order(n: usize, seed: u64, epoch: u64) -> Vec<usize> {
    let mut rng = SplitMix64::new(seed ^ epoch.wrapping_add(1).wrapping_mul(0xD6E8_FEB8_6659_FD93));
    let mut order: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        order.swap(i, rng.below(i + 1));
    }
    order
}

/// Samples in memory, batched in order or shuffled per epoch by a seed.
#[derive(Debug)]
pub struct MemorySource {
    /// Every sample, `N` of them.
    samples: Batch,
    batch_size: usize,
    shuffle: Option<u64>,
}

impl MemorySource {
    /// Samples with the shapes of [`Batch`] (`N` instead of `B`) and one id each; batches of
    /// `batch_size` (the last one may be smaller), shuffled per epoch with the seed `shuffle`,
    /// or in storage order if `None`.
    pub fn new(
        image: Tensor,
        depth: Tensor,
        labels: Tensor,
        mask: Tensor,
        ids: Vec<String>,
        batch_size: usize,
        shuffle: Option<u64>,
    ) -> Result<Self> {
        let s = image.size();
        let ok = s.len() == 4
            && s[1] == 3
            && depth.size() == [s[0], 1, s[2], s[3]]
            && labels.size() == [s[0], s[2], s[3]]
            && mask.size() == [s[0], 1, s[2], s[3]]
            && ids.len() as i64 == s[0]
            && image.kind() == Kind::Float
            && depth.kind() == Kind::Float
            && labels.kind() == Kind::Int64
            && mask.kind() == Kind::Bool;
        if !ok || batch_size == 0 {
            return Err(Error::InvalidArgument(format!(
                "MemorySource: expected image [N, 3, H, W] f32, depth [N, 1, H, W] f32, labels \
                 [N, H, W] i64, mask [N, 1, H, W] bool, N ids and batch_size > 0; got {:?} {:?}, \
                 {:?} {:?}, {:?} {:?}, {:?} {:?}, {} ids, batch_size {batch_size}",
                image.size(),
                image.kind(),
                depth.size(),
                depth.kind(),
                labels.size(),
                labels.kind(),
                mask.size(),
                mask.kind(),
                ids.len()
            )));
        }
        Ok(MemorySource {
            samples: Batch {
                image,
                depth,
                labels,
                mask,
                ids,
            },
            batch_size,
            shuffle,
        })
    }

    /// Batch size.
    pub fn batch_size(&self) -> usize {
        self.batch_size
    }

    fn batch(&self, idx: &[usize]) -> Batch {
        let i: Vec<i64> = idx.iter().map(|&i| i as i64).collect();
        let i = Tensor::from_slice(&i);
        let all = &self.samples;
        Batch {
            image: all.image.index_select(0, &i),
            depth: all.depth.index_select(0, &i),
            labels: all.labels.index_select(0, &i),
            mask: all.mask.index_select(0, &i),
            ids: idx.iter().map(|&k| all.ids[k].clone()).collect(),
        }
    }
}

impl BatchSource for MemorySource {
    fn len(&self) -> usize {
        self.samples.ids.len()
    }

    fn input_size(&self) -> [i64; 2] {
        let s = self.samples.image.size();
        [s[2], s[3]]
    }

    fn batches(&self, epoch: u64, skip: usize) -> Box<dyn Iterator<Item = Result<Batch>> + '_> {
        let order = match self.shuffle {
            Some(seed) => epoch_order(self.len(), seed, epoch),
            None => (0..self.len()).collect(),
        };
        let chunks: Vec<Vec<usize>> = order
            .chunks(self.batch_size)
            .skip(skip)
            .map(|c| c.to_vec())
            .collect();
        Box::new(chunks.into_iter().map(move |idx| Ok(self.batch(&idx))))
    }
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    fn source(n: i64, batch: usize, shuffle: Option<u64>) -> MemorySource {
        let o = (Kind::Float, Device::Cpu);
        MemorySource::new(
            Tensor::arange(n, o)
                .view([n, 1, 1, 1])
                .expand([n, 3, 2, 2], false)
                .contiguous(),
            Tensor::ones([n, 1, 2, 2], o),
            Tensor::zeros([n, 2, 2], (Kind::Int64, Device::Cpu)),
            Tensor::ones([n, 1, 2, 2], (Kind::Bool, Device::Cpu)),
            (0..n).map(|i| format!("s{i}")).collect(),
            batch,
            shuffle,
        )
        .unwrap()
    }

    fn ids(s: &MemorySource, epoch: u64, skip: usize) -> Vec<Vec<String>> {
        s.batches(epoch, skip).map(|b| b.unwrap().ids).collect()
    }

    #[test]
    fn order_is_a_seeded_permutation_per_epoch_and_skip_resumes_it() {
        let s = source(10, 3, Some(7));
        let e0 = ids(&s, 0, 0);
        assert_eq!(e0.len(), 4);
        assert_eq!(e0[3].len(), 1);
        let mut all: Vec<String> = e0.concat();
        all.sort();
        let mut want: Vec<String> = (0..10).map(|i| format!("s{i}")).collect();
        want.sort();
        assert_eq!(all, want);
        assert_eq!(e0, ids(&source(10, 3, Some(7)), 0, 0));
        assert_ne!(e0, ids(&s, 1, 0));
        assert_ne!(e0, ids(&source(10, 3, Some(8)), 0, 0));
        assert_eq!(ids(&s, 0, 2), e0[2..]);
        // The batch content follows the ids.
        let b = s.batches(0, 0).next().unwrap().unwrap();
        let first: i64 = b.ids[0][1..].parse().unwrap();
        assert_eq!(b.image.double_value(&[0, 0, 0, 0]) as i64, first);
        // Unshuffled: storage order.
        assert_eq!(ids(&source(4, 4, None), 3, 0), [["s0", "s1", "s2", "s3"]]);
    }

    #[test]
    fn wrong_shapes_are_errors() {
        let o = (Kind::Float, Device::Cpu);
        let err = MemorySource::new(
            Tensor::zeros([2, 3, 4, 4], o),
            Tensor::zeros([2, 1, 4, 5], o),
            Tensor::zeros([2, 4, 4], (Kind::Int64, Device::Cpu)),
            Tensor::ones([2, 1, 4, 4], (Kind::Bool, Device::Cpu)),
            vec!["a".into(), "b".into()],
            1,
            None,
        )
        .unwrap_err();
        assert!(err.to_string().contains("[2, 1, 4, 5]"), "{err}");
    }
}
