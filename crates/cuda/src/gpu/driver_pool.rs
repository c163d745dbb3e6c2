//! The CUDA driver's stream-ordered memory pool under cubecl's: what the device really holds.
//!
//! cubecl takes each page of its pool with `cuMemAllocAsync` from the device's default memory pool and
//! gives it back with `cuMemFreeAsync`. Under the `pages` layouts cubecl never gives a page back, so the
//! driver's pool holds what cubecl's reserved; under `driver:MIB` (umgen-cli's `memory_pool`) cubecl hands
//! free pages back during the step and the driver's pool reuses their memory for pages of other sizes, so
//! its high-water mark, not cubecl's sum of pages, is the memory the step took from the device.

/// The default memory pool of a CUDA device, in bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DriverPool {
    /// The most memory the pool has held from the device since the process started.
    pub reserved_high: u64,
    /// The most memory of it handed out at once (cubecl's pages, live or free in cubecl's pool).
    pub used_high: u64,
}

/// Raises the release threshold of every device's default memory pool to the whole device, so that the
/// memory cubecl hands back stays with the driver's pool for its next pages instead of going back to the
/// device at each synchronisation (the threshold is 0 by default).
pub fn keep_freed_memory() -> Result<(), cudarc::driver::DriverError> {
    use cudarc::driver::{result, sys};
    result::init()?;
    for index in 0..result::device::get_count()? {
        let pool = default_pool(index)?;
        let mut threshold = u64::MAX;
        // SAFETY: `pool` is the device's default pool; the attribute takes a `u64`, which `threshold` is.
        unsafe {
            sys::cuMemPoolSetAttribute(
                pool,
                sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD,
                (&mut threshold as *mut u64).cast(),
            )
            .result()?;
        }
    }
    Ok(())
}

/// The default memory pool of device `index` now; `None` when the driver cannot be read.
pub fn read(index: usize) -> Option<DriverPool> {
    use cudarc::driver::sys::CUmemPool_attribute::{
        CU_MEMPOOL_ATTR_RESERVED_MEM_HIGH, CU_MEMPOOL_ATTR_USED_MEM_HIGH,
    };
    let pool = default_pool(i32::try_from(index).ok()?).ok()?;
    let attribute = |attr| {
        let mut value = 0u64;
        // SAFETY: `pool` is the device's default pool; both attributes are `u64`s.
        unsafe { cudarc::driver::sys::cuMemPoolGetAttribute(pool, attr, (&mut value as *mut u64).cast()) }
            .result()
            .ok()
            .map(|()| value)
    };
    Some(DriverPool {
        reserved_high: attribute(CU_MEMPOOL_ATTR_RESERVED_MEM_HIGH)?,
        used_high: attribute(CU_MEMPOOL_ATTR_USED_MEM_HIGH)?,
    })
}

/// Device `index`'s default memory pool.
fn default_pool(index: i32) -> Result<cudarc::driver::sys::CUmemoryPool, cudarc::driver::DriverError> {
    use cudarc::driver::{result, sys};
    let device = result::device::get(index)?;
    let mut pool = std::ptr::null_mut();
    // SAFETY: `device` is a valid device handle and `pool` a place for the pool's handle.
    unsafe { sys::cuDeviceGetDefaultMemPool(&mut pool, device).result()? };
    Ok(pool)
}
