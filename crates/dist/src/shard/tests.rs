use super::Shards;
use crate::fake::{Fake, Starts};
use burn::backend::{Autodiff, Flex};
use burn::module::{Module, Param, ParamId};
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};
use std::sync::Arc;

type AD = Autodiff<Flex>;
type I = Flex;

fn ids(n: usize) -> Vec<ParamId> {
    (0..n).map(|_| ParamId::new()).collect()
}

#[test]
fn every_parameter_has_one_owner_and_the_shares_are_balanced() {
    let sizes_of = [10usize, 7, 5, 3, 3, 1, 0, 2];
    let id = ids(sizes_of.len());
    let sizes: Vec<(ParamId, usize)> = id.iter().copied().zip(sizes_of).collect();
    for world in 1..=5 {
        let plans: Vec<Shards> = (0..world).map(|r| Shards::from_sizes(&sizes, r, world)).collect();
        let mut seen = vec![0usize; sizes.len()];
        for (r, p) in plans.iter().enumerate() {
            for (k, i) in id.iter().enumerate() {
                assert_eq!(
                    p.owner(*i),
                    plans[0].owner(*i),
                    "world {world}: rank {r} agrees on {k}"
                );
            }
            for i in p.owned() {
                seen[id.iter().position(|x| *x == i).expect("a known id")] += 1;
            }
            // The loads are the owned elements, counted independently.
            let mine: usize = sizes
                .iter()
                .filter(|(i, _)| p.owner(*i) == Some(r))
                .map(|(_, n)| n)
                .sum();
            assert_eq!(p.loads()[r], mine, "world {world} rank {r}");
        }
        assert!(
            seen.iter().all(|&c| c == 1),
            "world {world}: each parameter owned once: {seen:?}"
        );
        let loads = plans[0].loads();
        let (max, min) = (
            loads.iter().max().copied().unwrap_or(0),
            loads.iter().min().copied().unwrap_or(0),
        );
        assert!(
            max - min <= 10,
            "world {world}: shares {loads:?} differ by more than the largest tensor"
        );
        assert_eq!(loads.iter().sum::<usize>(), 31);
    }
    // Largest first onto the least-loaded rank: 10 → 0, 7 → 1, 5 → 1, 3 → 0, 3 → 1, 2 → 0, 1 → 0, 0 → 0.
    let two = Shards::from_sizes(&sizes, 0, 2);
    let owners: Vec<usize> = id.iter().map(|i| two.owner(*i).unwrap_or(9)).collect();
    assert_eq!(owners, vec![0, 1, 1, 0, 1, 0, 1, 0]);
    assert_eq!(two.loads(), &[16, 15]);
    assert_eq!(two.owner(ParamId::new()), None);
}

/// (burn's derive recognises the backend parameter by its name, `B`.)
#[derive(Module, Debug)]
struct Net<B: Backend> {
    a: Param<Tensor<B, 1>>,
    b: Param<Tensor<B, 2>>,
    c: Param<Tensor<B, 1>>,
}

fn net(shift: f32) -> Net<AD> {
    let d = Default::default();
    let t1 = |v: &[f32]| {
        Param::from_tensor(
            Tensor::<AD, 1>::from_data(TensorData::new(v.to_vec(), [v.len()]), &d).add_scalar(shift),
        )
    };
    Net {
        a: t1(&[0.5, -1.0, 2.0]),
        b: Param::from_tensor(
            Tensor::<AD, 2>::from_data(TensorData::new(vec![1.0f32, 2.0, -0.5, 0.25], [2, 2]), &d)
                .add_scalar(shift)
                .require_grad(),
        ),
        c: t1(&[0.1, 0.2]),
    }
}

fn host(t: Tensor<I, 1>) -> Vec<f32> {
    t.into_data().to_vec::<f32>().unwrap_or_default()
}

#[test]
fn a_group_that_starts_collectives_gathers_in_buckets_and_settles_once() {
    let n = net(1.0);
    let shards = Shards::plan::<AD, _>(&n, 1, 2);
    // Sizes 3, 4, 2: b (4) → 0, a (3) → 1, c (2) → 1.
    let roots: Vec<usize> = [n.a.id, n.b.id, n.c.id]
        .map(|i| shards.owner(i).unwrap_or(9))
        .to_vec();
    assert_eq!(roots, vec![1, 0, 1]);
    let starts = Arc::new(Starts {
        rank: 1,
        ..Starts::default()
    });
    let mut group = Fake {
        rank: 1,
        starts: Some(starts.clone()),
        ..Fake::default()
    };
    // Buckets of at least 5 floats: [a, b], then [c], each tensor as it lies.
    let out = shards.gather_in::<AD, _>(n, &mut group, 20, 9).expect("gather");
    assert_eq!(
        *starts.log.lock().expect("lock"),
        vec!["broadcast [1, 0] [3] [2, 2]", "broadcast [1] [2]", "settle 3"]
    );
    // At most one tensor a bucket; the public gather makes one bucket of these few.
    starts.log.lock().expect("lock").clear();
    let again = shards.gather_in::<AD, _>(out, &mut group, 20, 1).expect("gather");
    let out = shards.gather::<AD, _>(again, &mut group).expect("gather");
    assert_eq!(
        *starts.log.lock().expect("lock"),
        vec![
            "broadcast [1] [3]",
            "broadcast [0] [2, 2]",
            "broadcast [1] [2]",
            "settle 3",
            "broadcast [1, 0, 1] [3] [2, 2] [2]",
            "settle 3"
        ]
    );
    let want = net(0.0);
    assert_eq!(
        host(out.a.val().inner()),
        host(want.a.val().inner().add_scalar(1.0)),
        "own: kept"
    );
    assert_eq!(
        host(out.b.val().inner().flatten(0, 1)),
        vec![1000.0; 4],
        "rank 0's: copied"
    );
    assert_eq!(
        host(out.c.val().inner()),
        host(want.c.val().inner().add_scalar(1.0))
    );
    assert!(out.b.val().is_require_grad());
    // A plan for another model names the parameter it lacks.
    let other = Shards::plan::<AD, _>(&net(0.0), 1, 2);
    let err = other
        .gather::<AD, _>(net(0.0), &mut group)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(err.contains("in no shard"), "{err}");
}
