//! Backend-specific paths without specialisation.
//!
//! The model is generic over `B: Backend`, and stable Rust cannot specialise a generic function for one
//! backend. Operations that have a faster path on a known training backend (the tiled attention, the
//! named matmul) instead offer that path as a function pointer typed for that backend, and [`same`] hands
//! it out when the caller's `B` is that backend.

use std::any::Any;
use std::sync::atomic::{AtomicUsize, Ordering};

/// How many passes a family of kernels refused (or failed to launch) in this process, so that burn's
/// decomposition ran them instead; the first refusal is logged. A count for the log and the benchmarks,
/// not a choice: what runs is the caller's [`crate::Kernels`].
#[derive(Debug)]
pub(crate) struct Fallbacks {
    count: AtomicUsize,
    /// What the kernels compute, for the log.
    what: &'static str,
}

impl Fallbacks {
    /// Nothing fallen back.
    pub(crate) const fn new(what: &'static str) -> Self {
        Self {
            count: AtomicUsize::new(0),
            what,
        }
    }

    /// How many passes fell back to the decomposition in this process.
    pub(crate) fn count(&self) -> usize {
        self.count.load(Ordering::Relaxed)
    }

    /// Counts a pass the kernels refused for `why`; logs the first.
    #[cfg_attr(not(feature = "cuda"), allow(dead_code))]
    pub(crate) fn fell_back(&self, why: &str) {
        if self.count.fetch_add(1, Ordering::Relaxed) == 0 {
            tracing::warn!(
                "the {} kernels refused {why}; the decomposition runs it (counted in fallbacks)",
                self.what
            );
        }
    }
}

/// `f` as a `G` when `F` and `G` are one type (function pointers are `'static` values, so `Any` can tell);
/// `None` otherwise.
pub(crate) fn same<F: Copy + 'static, G: Copy + 'static>(f: F) -> Option<G> {
    (&f as &dyn Any).downcast_ref::<G>().copied()
}

#[cfg(test)]
mod tests {
    use super::{Fallbacks, same};

    #[test]
    fn fallbacks_are_counted() {
        let c = Fallbacks::new("test");
        assert_eq!(c.count(), 0);
        c.fell_back("a shape");
        c.fell_back("another");
        assert_eq!(c.count(), 2);
    }

    #[test]
    fn only_the_same_function_type_passes() {
        fn one(x: u32) -> u32 {
            x + 1
        }
        let f: fn(u32) -> u32 = one;
        assert_eq!(same::<_, fn(u32) -> u32>(f).map(|g| g(1)), Some(2));
        assert!(same::<_, fn(u64) -> u64>(f).is_none());
    }
}
