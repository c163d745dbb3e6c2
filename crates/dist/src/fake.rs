//! A process group for unit tests: one rank of two whose "mean" adds one to every element (a test can
//! tell reduced values from unreduced ones) and records each collective's length; given a handle that
//! starts collectives ([`Starts`]), it hands everything to that handle instead.

use crate::error::Result;
use crate::group::{AsyncCollective, Group, ProcessGroup};
use burn::backend::Flex;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};
use std::sync::{Arc, Mutex};

/// The fake group ([module docs](self)).
#[derive(Default)]
pub(crate) struct Fake {
    /// This rank (of two).
    pub(crate) rank: usize,
    /// The length of each collective the group ran itself.
    pub(crate) calls: Vec<usize>,
    /// What starts collectives, if this group can.
    pub(crate) starts: Option<Arc<dyn AsyncCollective<Flex>>>,
}

impl Group for Fake {
    fn rank(&self) -> usize {
        self.rank
    }
    fn world_size(&self) -> usize {
        2
    }
    fn barrier(&mut self) -> Result<()> {
        Ok(())
    }
    fn finish(&mut self) {}
    fn backend(&self) -> &'static str {
        "fake"
    }
}

impl ProcessGroup<Flex> for Fake {
    fn all_reduce_mean(&mut self, t: Tensor<Flex, 1>) -> Result<Tensor<Flex, 1>> {
        assert!(
            self.starts.is_none(),
            "a group that starts collectives runs them there"
        );
        self.calls.push(t.dims()[0]);
        Ok(t.add_scalar(1.0))
    }
    fn broadcast(&mut self, t: Tensor<Flex, 1>, _root: usize) -> Result<Tensor<Flex, 1>> {
        assert!(
            self.starts.is_none(),
            "a group that starts collectives runs them there"
        );
        self.calls.push(t.dims()[0]);
        Ok(t)
    }
    fn async_collective(&self) -> Option<Arc<dyn AsyncCollective<Flex>>> {
        self.starts.clone()
    }
}

/// Started collectives that log themselves: a mean adds one (and says whether the backward pass had
/// `returned`), a broadcast keeps this `rank`'s tensors and fills another root's with
/// `1000 · (root + 1)`; settling hands the tensors back.
#[derive(Default)]
pub(crate) struct Starts {
    /// The rank whose tensors a broadcast keeps.
    pub(crate) rank: usize,
    /// What was started and settled, in order.
    pub(crate) log: Mutex<Vec<String>>,
    /// Set by a test once its backward pass has returned.
    pub(crate) returned: Mutex<bool>,
}

fn typed(t: FloatTensor<Flex>) -> Tensor<Flex, 1> {
    Tensor::from_primitive(TensorPrimitive::Float(t))
}

impl Starts {
    fn note(&self, line: String) {
        if let Ok(mut log) = self.log.lock() {
            log.push(line);
        }
    }
}

impl AsyncCollective<Flex> for Starts {
    fn start_mean(&self, bucket: Vec<FloatTensor<Flex>>) -> Result<Vec<FloatTensor<Flex>>> {
        let during = self.returned.lock().map(|r| !*r).unwrap_or(false);
        let n: usize = bucket.iter().map(|t| t.shape().num_elements()).sum();
        self.note(format!("start {n} {}", if during { "during" } else { "after" }));
        Ok(bucket
            .into_iter()
            .map(|t| typed(t).add_scalar(1.0).into_primitive().tensor())
            .collect())
    }
    fn start_broadcast(
        &self,
        bucket: Vec<FloatTensor<Flex>>,
        roots: &[usize],
    ) -> Result<Vec<FloatTensor<Flex>>> {
        let shapes: Vec<String> = bucket
            .iter()
            .map(|t| format!("{:?}", t.shape().to_vec()))
            .collect();
        self.note(format!("broadcast {roots:?} {}", shapes.join(" ")));
        let other = |t, r: usize| typed(t).zeros_like().add_scalar(1000.0 * (r + 1) as f32);
        Ok(bucket
            .into_iter()
            .zip(roots)
            .map(|(t, &r)| {
                if r == self.rank {
                    t
                } else {
                    other(t, r).into_primitive().tensor()
                }
            })
            .collect())
    }
    fn settle(&self, started: Vec<FloatTensor<Flex>>) -> Result<Vec<FloatTensor<Flex>>> {
        self.note(format!("settle {}", started.len()));
        Ok(started)
    }
}
