use super::*;

const GIB: u64 = 1 << 30;

fn pages(mib: u64) -> anyhow::Result<Vec<Pool>> {
    PoolLayout::parse(&format!("pages:{mib}"))?
        .pools()
        .context("a pages layout has pools")
}

/// Sizes from a byte to 1 TiB: powers of two and the points between them.
fn sizes() -> impl Iterator<Item = u64> {
    (0..40).flat_map(|e| {
        let p = 1u64 << e;
        [p, p + 1, p + p / 3, p + p / 2, 2 * p - 1]
    })
}

#[test]
fn every_tensor_finds_a_pool_and_no_sliced_page_passes_the_largest() -> anyhow::Result<()> {
    for mib in [32, 256, 1024, 8192] {
        let pools = pages(mib)?;
        let largest = mib * MIB;
        for size in sizes() {
            let pool = pool_for(&pools, size).unwrap_or_else(|| panic!("pages:{mib}: no pool for {size} B"));
            match pool {
                Pool::Sliced { page, .. } => {
                    assert!(page <= largest, "pages:{mib}: {size} B in a {page} B page");
                    assert!(
                        size <= page,
                        "pages:{mib}: {size} B does not fit its {page} B page"
                    );
                }
                // A tensor beyond the largest page reserves at most twice its size.
                Pool::Exclusive { max_alloc } => {
                    assert!(
                        size > largest || size == 0,
                        "pages:{mib}: {size} B alone in a page"
                    );
                    assert!(
                        max_alloc < 2 * size.max(1) || size == 0,
                        "pages:{mib}: {size} B in a bucket to {max_alloc}"
                    );
                }
            }
        }
    }
    Ok(())
}

#[test]
fn small_tensors_share_small_pages_as_in_cubecl() -> anyhow::Result<()> {
    // cubecl's geometry from a 1 GiB page: pages of 256, 64 and 16 MiB holding slices of at most a
    // half, a quarter and an eighth of them.
    let pools = pages(1024)?;
    assert_eq!(
        pools[..5],
        [
            Pool::Exclusive { max_alloc: 0 },
            Pool::Sliced {
                page: 16 * MIB,
                max_slice: 2 * MIB
            },
            Pool::Sliced {
                page: 64 * MIB,
                max_slice: 16 * MIB
            },
            Pool::Sliced {
                page: 256 * MIB,
                max_slice: 128 * MIB
            },
            Pool::Sliced {
                page: GIB,
                max_slice: GIB
            },
        ]
    );
    assert_eq!(pool_for(&pools, 4096), Some(pools[1]));
    assert_eq!(pool_for(&pools, 300 * MIB), Some(pools[4]));
    // Within 20 % of a page, a tensor takes the page rather than the next pool.
    assert_eq!(pool_for(&pools, 60 * MIB), Some(pools[2]));
    assert_eq!(
        pool_for(&pools, 3 * GIB / 2),
        Some(Pool::Exclusive { max_alloc: 2 * GIB })
    );
    Ok(())
}

#[test]
fn the_variable_names_what_it_refuses() -> anyhow::Result<()> {
    assert_eq!(PoolLayout::parse("cubecl")?, PoolLayout::Cubecl);
    assert_eq!(
        PoolLayout::parse(" pages:64 ")?,
        PoolLayout::Pages { largest: 64 * MIB }
    );
    assert_eq!(PoolLayout::Cubecl.pools(), None);
    assert_eq!(
        PoolLayout::default().to_string(),
        format!("pages:{DEFAULT_LARGEST_PAGE_MIB}")
    );
    assert_eq!(PoolLayout::Pages { largest: GIB }.to_string(), "pages:1024");
    for (value, says) in [
        ("sliced", "expected `cubecl` or `pages:MIB`"),
        ("pages:1g", "`1g` is not a whole number"),
        ("pages:1000", "power of two"),
        ("pages:16", "power of two from 32"),
        ("pages:131072", "to 65536"),
    ] {
        let Err(err) = PoolLayout::parse(value) else {
            panic!("{value} was accepted");
        };
        let err = err.to_string();
        assert!(err.contains(value.trim()) && err.contains(says), "{value}: {err}");
    }
    Ok(())
}
