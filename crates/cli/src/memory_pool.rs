//! `UMGEN_MEMORY_POOL`: how the CUDA memory pool lays out the memory it reserves from the driver.
//!
//! cubecl's default layout takes its largest page as a quarter of the device's memory and slices pages a
//! quarter, a sixteenth, … of that: on an 80 GiB H100 a tensor of 0.3–2.5 GiB takes a slice of a 5 GiB
//! page and one of 40–300 MiB a slice of a 1.25 GiB page, so a training step's pool reserves well beyond
//! its live tensors. `pages:MIB` (the default, `pages:1024`) keeps cubecl's geometry below a largest sliced
//! page of MIB and gives each larger tensor a page of its own, in buckets of doubling size; `cubecl` keeps
//! cubecl's layout.

use anyhow::{Context, bail};

/// The environment variable that chooses the layout.
pub const VAR: &str = "UMGEN_MEMORY_POOL";

/// The largest shared page (MiB) when the variable is unset: on an H200, `bench train` reserved 25 %
/// less for `small` and 17 % less for `paper` than with cubecl's layout, in the same step time; pages of
/// 64 MiB to 4 GiB differ by about 1 GiB (docs/decisions/014-memory-pool-layout.md).
pub const DEFAULT_LARGEST_PAGE_MIB: u64 = 1024;

const MIB: u64 = 1 << 20;

/// Pages below this size are not split further (cubecl's own lower bound).
const SMALLEST_SPLIT: u64 = 32 * MIB;

/// Buckets of tensors with a page of their own reach this size (1 TiB: beyond any device).
const LARGEST_TENSOR: u64 = 1 << 40;

/// A layout of the memory pool.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoolLayout {
    /// cubecl's own layout (pages sized from the device's memory).
    Cubecl,
    /// Sliced pages up to `largest` bytes; larger tensors get a page each.
    Pages {
        /// The largest sliced page, in bytes.
        largest: u64,
    },
}

/// One pool of a layout; an allocation goes to the first pool that accepts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pool {
    /// Pages of `page` bytes holding several tensors of up to `max_slice` bytes each.
    Sliced {
        /// Bytes per page.
        page: u64,
        /// The largest tensor a slice holds (cubecl also takes a tensor within 20 % of `page`).
        max_slice: u64,
    },
    /// A page per tensor of up to `max_alloc` bytes, reused by the next tensor that fits it.
    Exclusive {
        /// The largest tensor the pool takes.
        max_alloc: u64,
    },
}

impl Pool {
    /// Whether cubecl puts a tensor of `size` bytes in this pool (its `MemoryPool::accept`).
    pub fn accepts(self, size: u64) -> bool {
        match self {
            Pool::Sliced { page, max_slice } => {
                size <= max_slice || page.checked_sub(size).is_some_and(|spare| spare * 5 < page)
            }
            Pool::Exclusive { max_alloc } => size <= max_alloc,
        }
    }
}

impl PoolLayout {
    /// The layout `UMGEN_MEMORY_POOL` names, or the default when it is unset or empty.
    pub fn from_env() -> anyhow::Result<Self> {
        match std::env::var(VAR) {
            Ok(v) if !v.trim().is_empty() => {
                Self::parse(&v).with_context(|| format!("environment variable {VAR}"))
            }
            Ok(_) | Err(std::env::VarError::NotPresent) => Ok(Self::default()),
            Err(std::env::VarError::NotUnicode(v)) => bail!("environment variable {VAR}: {v:?} is not UTF-8"),
        }
    }

    /// Parses `cubecl` or `pages:MIB` (MIB a power of two from 32 to 65536).
    pub fn parse(value: &str) -> anyhow::Result<Self> {
        let value = value.trim();
        if value == "cubecl" {
            return Ok(Self::Cubecl);
        }
        let Some(mib) = value.strip_prefix("pages:") else {
            bail!("`{value}`: expected `cubecl` or `pages:MIB` (e.g. pages:{DEFAULT_LARGEST_PAGE_MIB})");
        };
        let mib: u64 = mib
            .parse()
            .map_err(|_| anyhow::anyhow!("`{value}`: `{mib}` is not a whole number of MiB"))?;
        if !(32..=65536).contains(&mib) || !mib.is_power_of_two() {
            bail!("`{value}`: the largest page must be a power of two from 32 to 65536 MiB");
        }
        Ok(Self::Pages { largest: mib * MIB })
    }

    /// The pools in the order cubecl tries them; `None` for cubecl's own layout.
    pub fn pools(self) -> Option<Vec<Pool>> {
        let Self::Pages { largest } = self else {
            return None;
        };
        // cubecl's first pool: zero-byte tensors, which cannot take a slice.
        let mut pools = vec![Pool::Exclusive { max_alloc: 0 }];
        // cubecl's geometry below the largest page: each page a quarter of the next, slices of the k-th
        // page from the top at most page / 2^k, so small tensors share small pages.
        let mut split = Vec::new();
        let (mut page, mut k) = (largest, 1);
        while page >= SMALLEST_SPLIT {
            page /= 4;
            split.push(Pool::Sliced {
                page,
                max_slice: page >> k,
            });
            k += 1;
        }
        pools.extend(split.into_iter().rev());
        pools.push(Pool::Sliced {
            page: largest,
            max_slice: largest,
        });
        let mut max_alloc = largest;
        while max_alloc < LARGEST_TENSOR {
            max_alloc *= 2;
            pools.push(Pool::Exclusive { max_alloc });
        }
        Some(pools)
    }
}

/// The first of `pools` that takes a tensor of `size` bytes, as cubecl chooses it.
pub fn pool_for(pools: &[Pool], size: u64) -> Option<Pool> {
    pools.iter().copied().find(|p| p.accepts(size))
}

impl Default for PoolLayout {
    fn default() -> Self {
        Self::Pages {
            largest: DEFAULT_LARGEST_PAGE_MIB * MIB,
        }
    }
}

impl std::fmt::Display for PoolLayout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Cubecl => write!(f, "cubecl"),
            Self::Pages { largest } => write!(f, "pages:{}", largest / MIB),
        }
    }
}

/// The layout [`init`] applied in this process, if it ran.
static APPLIED: std::sync::OnceLock<PoolLayout> = std::sync::OnceLock::new();

/// The layout [`init`] gave this process's CUDA devices: `None` before it (devices then start with
/// cubecl's own) or without CUDA.
pub fn applied() -> Option<PoolLayout> {
    APPLIED.get().copied()
}

/// Applies `UMGEN_MEMORY_POOL` to every CUDA device this process starts; call before any CUDA work.
#[cfg(feature = "cuda")]
pub fn init() -> anyhow::Result<PoolLayout> {
    // A second call (a tool running two commands) keeps the first layout: devices already started keep it.
    if let Some(layout) = applied() {
        return Ok(layout);
    }
    let layout = apply(PoolLayout::from_env()?);
    Ok(*APPLIED.get_or_init(|| layout))
}

#[cfg(feature = "cuda")]
fn apply(layout: PoolLayout) -> PoolLayout {
    #[cfg(feature = "patched-cubecl")]
    if let Some(pools) = layout.pools() {
        use burn::cubecl::cuda::{MemoryConfiguration, MemoryPoolOptions, PoolType};
        let pool_options = pools
            .into_iter()
            .map(|p| MemoryPoolOptions {
                pool_type: match p {
                    Pool::Sliced { page, max_slice } => PoolType::SlicedPages {
                        page_size: page,
                        max_slice_size: max_slice,
                    },
                    Pool::Exclusive { max_alloc } => PoolType::ExclusivePages {
                        max_alloc_size: max_alloc,
                    },
                },
                // Pages stay: a training step needs the same tensors again, and freeing a page waits
                // for the device.
                dealloc_period: None,
            })
            .collect();
        burn::cubecl::cuda::set_memory_configuration(MemoryConfiguration::Custom { pool_options });
    }
    // `set_memory_configuration` is an API of the vendored cubecl-cuda (vendor/README.md).
    #[cfg(not(feature = "patched-cubecl"))]
    if layout != PoolLayout::Cubecl {
        tracing::warn!("{VAR}={layout} needs the patched cubecl-cuda; cubecl's own layout is used");
        return PoolLayout::Cubecl;
    }
    layout
}

#[cfg(test)]
#[path = "memory_pool_tests.rs"]
mod tests;
