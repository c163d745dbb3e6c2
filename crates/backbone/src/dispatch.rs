//! Backend-specific paths without specialisation.
//!
//! The model is generic over `B: Backend`, and stable Rust cannot specialise a generic function for one
//! backend. Operations that have a faster path on a known training backend (the tiled attention, the
//! named matmul) instead offer that path as a function pointer typed for that backend, and [`same`] hands
//! it out when the caller's `B` is that backend.

use std::any::Any;

/// `f` as a `G` when `F` and `G` are one type (function pointers are `'static` values, so `Any` can tell);
/// `None` otherwise.
pub(crate) fn same<F: Copy + 'static, G: Copy + 'static>(f: F) -> Option<G> {
    (&f as &dyn Any).downcast_ref::<G>().copied()
}

#[cfg(test)]
mod tests {
    use super::same;

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
