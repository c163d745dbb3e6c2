//! Backend-specific paths without specialisation.
//!
//! The model is generic over `B: Backend`, and stable Rust cannot specialise a generic function for one
//! backend. Operations that have a faster path on a known training backend (the tiled attention, the
//! named matmul) instead offer that path as a function pointer typed for that backend, and [`same`] hands
//! it out when the caller's `B` is that backend.

use std::any::Any;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// A process-wide choice between a hand-written kernel and burn's decomposition of the same operation
/// (the kernel unless told otherwise), with a count of the passes the kernel refused or failed to launch.
#[derive(Debug)]
pub(crate) struct Choice {
    burn: AtomicBool,
    fallbacks: AtomicUsize,
    /// What the kernel computes, for the log.
    what: &'static str,
}

impl Choice {
    /// The kernel chosen, nothing fallen back.
    pub(crate) const fn new(what: &'static str) -> Self {
        Self {
            burn: AtomicBool::new(false),
            fallbacks: AtomicUsize::new(0),
            what,
        }
    }

    /// Chooses burn's decomposition (`true`) or the kernel from now on.
    pub(crate) fn set_burn(&self, burn: bool) {
        self.burn.store(burn, Ordering::Relaxed);
    }

    /// Whether burn's decomposition was chosen.
    pub(crate) fn burn(&self) -> bool {
        self.burn.load(Ordering::Relaxed)
    }

    /// How many passes fell back to the decomposition in this process.
    pub(crate) fn fallbacks(&self) -> usize {
        self.fallbacks.load(Ordering::Relaxed)
    }

    /// Counts a pass the kernel refused for `why`; logs the first.
    #[cfg_attr(not(feature = "cuda"), allow(dead_code))]
    pub(crate) fn fell_back(&self, why: &str) {
        if self.fallbacks.fetch_add(1, Ordering::Relaxed) == 0 {
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
    use super::{Choice, same};

    #[test]
    fn a_choice_counts_its_fallbacks_and_remembers_burn() {
        let c = Choice::new("test");
        assert!(!c.burn());
        c.set_burn(true);
        assert!(c.burn());
        c.fell_back("a shape");
        c.fell_back("another");
        assert_eq!(c.fallbacks(), 2);
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
