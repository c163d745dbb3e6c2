//! Ranks as threads of one test process, over loopback: the TCP ring's collectives against a direct
//! computation, bucketed gradient averaging against the mean of the ranks' gradients, and the failures
//! the rendezvous and the watchdog must report.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use burn::backend::{Autodiff, Flex};
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::optim::GradientsParams;
use burn::tensor::{Tensor, TensorData};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use umgen_dist::{
    DistEnv, Group, ProcessGroup, Session, SessionOptions, Shards, TcpGroup, all_reduce_grads,
    broadcast_module, same_on_all_ranks,
};

type B = Flex;
type AB = Autodiff<Flex>;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn env(rank: usize, world: usize, port: u16) -> DistEnv {
    DistEnv {
        rank,
        world_size: world,
        local_rank: rank,
        local_world_size: world,
        master_addr: "127.0.0.1".into(),
        master_port: port,
        source: "test",
    }
}

fn options(secs: u64) -> SessionOptions {
    SessionOptions {
        timeout: Duration::from_secs(secs),
        ..Default::default()
    }
}

/// Runs `f(rank, group)` on `world` ranks (threads) and returns their results in rank order.
fn on_ranks<T: Send + 'static>(
    world: usize,
    f: impl Fn(usize, TcpGroup) -> T + Send + Sync + 'static,
) -> Vec<T> {
    let port = free_port();
    let f = Arc::new(f);
    let handles: Vec<_> = (0..world)
        .map(|r| {
            let f = f.clone();
            std::thread::spawn(move || {
                let s =
                    Session::connect(env(r, world, port), "same", &options(20), || Ok(vec![7, 7])).unwrap();
                assert_eq!(s.payload, vec![7, 7], "rank 0's payload reaches rank {r}");
                f(r, TcpGroup::new(s))
            })
        })
        .collect();
    handles.into_iter().map(|h| h.join().unwrap()).collect()
}

fn values(rank: usize, n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| ((i * 31 + rank * 17) % 97) as f32 * 0.37 - 11.0 + rank as f32 * 0.001)
        .collect()
}

fn tensor(v: Vec<f32>) -> Tensor<B, 1> {
    let n = v.len();
    Tensor::from_data(TensorData::new(v, [n]), &Default::default())
}

fn host(t: Tensor<B, 1>) -> Vec<f32> {
    t.into_data().into_vec::<f32>().unwrap()
}

#[test]
fn all_reduce_and_broadcast_match_a_direct_computation() {
    for world in [1, 2, 3, 4] {
        // Lengths below, at and above the number of ranks, and uneven chunks.
        for n in [1usize, 3, 4, 1001] {
            let out = on_ranks(world, move |r, mut g| {
                let mean = host(g.all_reduce_mean(tensor(values(r, n))).unwrap());
                let bcast = host(g.broadcast(tensor(values(r, n)), 0).unwrap());
                let last = host(g.broadcast(tensor(values(r, n)), world - 1).unwrap());
                g.barrier().unwrap();
                g.finish();
                (mean, (bcast, last))
            });
            let want: Vec<f64> = (0..n)
                .map(|i| (0..world).map(|r| f64::from(values(r, n)[i])).sum::<f64>() / world as f64)
                .collect();
            for (r, (mean, (bcast, last))) in out.iter().enumerate() {
                for (a, b) in mean.iter().zip(&want) {
                    assert!(
                        (f64::from(*a) - b).abs() < 1e-4,
                        "world {world} n {n} rank {r}: {a} vs {b}"
                    );
                }
                assert_eq!(mean, &out[0].0, "bit-identical on every rank");
                assert_eq!(bcast, &values(0, n), "rank 0's values");
                assert_eq!(last, &values(world - 1, n), "the last rank's values");
            }
        }
    }
}

#[test]
fn bucketed_gradients_are_the_mean_of_the_ranks_gradients() {
    let model = |_: usize| {
        let dev = Default::default();
        <AB as burn::tensor::backend::Backend>::seed(&dev, 5);
        LinearConfig::new(6, 5).init::<AB>(&dev)
    };
    let grads_of = |r: usize, m: &Linear<AB>| {
        let x = Tensor::<AB, 2>::from_data(TensorData::new(values(r, 12), [2, 6]), &Default::default());
        GradientsParams::from_grads(m.forward(x).powf_scalar(2.0).sum().backward(), m)
    };
    let flat = |m: &Linear<AB>, g: &GradientsParams| {
        let w = g.get::<B, 2>(m.weight.id).unwrap();
        let b = g.get::<B, 1>(m.bias.as_ref().unwrap().id).unwrap();
        let mut v = host(w.flatten(0, 1));
        v.extend(host(b));
        v
    };
    let world = 3;
    let weights = |m: &Linear<AB>| {
        let mut v = host(m.weight.val().inner().flatten(0, 1));
        v.extend(host(m.bias.as_ref().unwrap().val().inner()));
        v
    };
    let out = on_ranks(world, move |r, mut g| {
        // Rank-dependent initial weights: the broadcast must replace them with rank 0's.
        let m = model(0).map(&mut Shift(r as f32));
        let m = broadcast_module::<AB, _>(m, &mut g, 64).unwrap();
        let local = flat(&m, &grads_of(r, &m));
        // A 64-byte bucket: several collectives for 35 floats.
        let avg = all_reduce_grads::<AB, _>(&m, grads_of(r, &m), &mut g, 64).unwrap();
        g.finish();
        (weights(&m), local, flat(&m, &avg))
    });
    for (r, (w, _, avg)) in out.iter().enumerate() {
        assert_eq!(w, &out[0].0, "rank {r} has rank 0's weights");
        assert_eq!(avg, &out[0].2, "rank {r}: bit-identical averages");
    }
    assert_ne!(out[0].1, out[1].1, "the ranks' own gradients differ");
    for (k, got) in out[0].2.iter().enumerate() {
        let want = out.iter().map(|o| o.1[k]).sum::<f32>() / world as f32;
        assert!(
            (got - want).abs() < 1e-4 * want.abs().max(1.0),
            "{k}: {got} vs {want}"
        );
    }
}

#[test]
fn a_sharded_step_takes_each_parameter_from_its_owner() {
    // Eight parameters of five sizes over three ranks; rank-dependent values, so the result tells which
    // rank each parameter came from.
    let model = |r: usize| {
        let dev = Default::default();
        [(6, 5), (3, 3), (5, 1), (2, 7)]
            .map(|(i, o)| LinearConfig::new(i, o).init::<AB>(&dev))
            .to_vec()
            .map(&mut Fill { rank: r, k: 0 })
    };
    let flat = |m: &Vec<Linear<AB>>| -> Vec<Vec<f32>> {
        m.iter()
            .flat_map(|l| {
                [
                    host(l.weight.val().inner().flatten(0, 1)),
                    host(l.bias.as_ref().unwrap().val().inner()),
                ]
            })
            .collect()
    };
    let world = 3;
    let out = on_ranks(world, move |r, mut g| {
        let m = model(r);
        let shards = Shards::plan::<AB, _>(&m, r, world);
        let owners: Vec<usize> = m
            .iter()
            .flat_map(|l| [l.weight.id, l.bias.as_ref().unwrap().id])
            .map(|id| shards.owner(id).unwrap())
            .collect();
        let m = shards.gather::<AB, _>(m, &mut g).unwrap();
        let grad = m[0].weight.val().is_require_grad();
        g.finish();
        (flat(&m), owners, grad)
    });
    let owners = &out[0].1;
    let mut used: Vec<usize> = owners.clone();
    used.sort_unstable();
    used.dedup();
    assert_eq!(used, vec![0, 1, 2], "every rank owns a share: {owners:?}");
    for (r, (values, o, grad)) in out.iter().enumerate() {
        assert_eq!(o, owners, "rank {r} plans the same owners");
        assert!(grad, "parameters stay trainable");
        for (k, v) in values.iter().enumerate() {
            assert_eq!(
                v,
                &flat(&model(owners[k]))[k],
                "rank {r}, parameter {k}: its owner's values"
            );
        }
    }
}

/// Sets float parameter `k` (module order) of rank `rank` to `1000·rank + 100·k + 0.5·i`.
struct Fill {
    rank: usize,
    k: usize,
}

impl burn::module::ModuleMapper<AB> for Fill {
    fn map_float<const D: usize>(
        &mut self,
        p: burn::module::Param<Tensor<AB, D>>,
    ) -> burn::module::Param<Tensor<AB, D>> {
        let base = 1000.0 * self.rank as f32 + 100.0 * self.k as f32;
        self.k += 1;
        p.map(|t| {
            let shape = t.shape();
            let n = shape.num_elements();
            let v: Vec<f32> = (0..n).map(|i| base + 0.5 * i as f32).collect();
            Tensor::<AB, 1>::from_data(TensorData::new(v, [n]), &t.device())
                .reshape(shape)
                .require_grad()
        })
    }
}

/// Adds a constant to every float parameter.
struct Shift(f32);

impl burn::module::ModuleMapper<AB> for Shift {
    fn map_float<const D: usize>(
        &mut self,
        p: burn::module::Param<Tensor<AB, D>>,
    ) -> burn::module::Param<Tensor<AB, D>> {
        let s = self.0;
        p.map(|t| Tensor::from_inner(t.inner().add_scalar(s)).require_grad())
    }
}

#[test]
fn ranks_that_disagree_on_a_value_all_fail_and_name_it() {
    // Equal everywhere, beyond f32's 24-bit mantissa: accepted.
    let big = (1u64 << 40) + 3;
    let out = on_ranks(3, move |_, mut g| {
        let r = same_on_all_ranks::<B>(&mut g, big, "the step", &Default::default());
        g.finish();
        r.is_ok()
    });
    assert_eq!(out, vec![true; 3]);
    // Rank 2 differs by one in the low bits: every rank fails, rank 2 names both values.
    let out = on_ranks(3, move |r, mut g| {
        let v = if r == 2 { big + 1 } else { big };
        let e = same_on_all_ranks::<B>(&mut g, v, "the step", &Default::default())
            .err()
            .map(|e| e.to_string());
        g.finish();
        e
    });
    assert!(out.iter().all(Option::is_some), "{out:?}");
    let two = out[2].as_deref().unwrap_or_default();
    assert!(
        two.contains("rank 2") && two.contains(&(big + 1).to_string()) && two.contains(&big.to_string()),
        "{two}"
    );
}

#[test]
fn mismatched_ranks_are_refused_by_name() {
    let port = free_port();
    let a = std::thread::spawn(move || {
        Session::connect(env(0, 2, port), "config-a", &options(10), || Ok(vec![]))
    });
    let b = std::thread::spawn(move || {
        Session::connect(env(1, 2, port), "config-b", &options(10), || Ok(vec![]))
    });
    let ea = a.join().unwrap().unwrap_err().to_string();
    let eb = b.join().unwrap().unwrap_err().to_string();
    assert!(ea.contains("rank 1 runs another configuration"), "{ea}");
    assert!(
        eb.contains("refused by rank 0") && eb.contains("another configuration"),
        "{eb}"
    );

    // A rank that never comes: rank 0 gives up after the timeout and names it.
    let t0 = Instant::now();
    let e = Session::connect(env(0, 3, free_port()), "x", &options(1), || Ok(vec![]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("timed out waiting for rank(s) 1, 2"), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(5));
}

#[test]
fn a_dead_rank_fails_the_others_naming_it() {
    let port = free_port();
    let reasons = Arc::new(Mutex::new(Vec::<String>::new()));
    let mut handles = Vec::new();
    for r in 0..3 {
        let reasons = reasons.clone();
        handles.push(std::thread::spawn(move || {
            let opts = SessionOptions {
                timeout: Duration::from_secs(3),
                on_failure: Arc::new(move |why: &str| reasons.lock().unwrap().push(why.to_string())),
            };
            let s = Session::connect(env(r, 3, port), "same", &opts, || Ok(vec![])).unwrap();
            let mut g = TcpGroup::new(s);
            g.barrier().unwrap();
            if r == 2 {
                // Rank 2 dies: its sockets close without a goodbye.
                return None;
            }
            let t0 = Instant::now();
            let e = g.all_reduce_mean(tensor(vec![1.0; 8])).unwrap_err().to_string();
            Some((e, t0.elapsed()))
        }));
    }
    let out: Vec<_> = handles.into_iter().map(|h| h.join().unwrap()).collect();
    for (r, o) in out.iter().take(2).enumerate() {
        let (e, took) = o.as_ref().unwrap();
        assert!(e.contains(&format!("rank {r}")) && e.contains("rank 2"), "{e}");
        assert!(*took < Duration::from_secs(10), "rank {r} waited {took:?}");
    }
    std::thread::sleep(Duration::from_millis(500));
    let reasons = reasons.lock().unwrap();
    assert!(
        reasons.iter().any(|w| w.contains("rank 2 exited")),
        "the watchdog names rank 2: {reasons:?}"
    );
}

#[test]
fn a_hung_rank_fails_the_others_within_the_timeout() {
    let port = free_port();
    let handles: Vec<_> = (0..3)
        .map(|r| {
            std::thread::spawn(move || {
                let s = Session::connect(env(r, 3, port), "same", &options(2), || Ok(vec![])).unwrap();
                let mut g = TcpGroup::new(s);
                g.barrier().unwrap();
                if r == 1 {
                    // Alive (its heartbeats go on) but never joins the next collective.
                    std::thread::sleep(Duration::from_secs(8));
                    return None;
                }
                let t0 = Instant::now();
                let e = g.all_reduce_mean(tensor(vec![1.0; 8])).unwrap_err().to_string();
                Some((e, t0.elapsed()))
            })
        })
        .collect();
    let out: Vec<_> = handles.into_iter().map(|h| h.join().unwrap()).collect();
    for o in [&out[0], &out[2]] {
        let (e, took) = o.as_ref().unwrap();
        assert!(e.contains("rank 1 has not reached collective #2"), "{e}");
        assert!(*took < Duration::from_secs(6), "waited {took:?}");
    }
}
