//! The host's draw (`draw.cu`): the same rules, the same candidates and probabilities, the same Philox
//! numbers, so that the host and a GPU draw the same tokens from the same logits.

use super::host::{HostExec, Store};
use umgen_cuda::ops::{BOX_WORDS, DRAW_KMAX, Draw, ExecError, GroupRun, Rule};
use umgen_eval::collision::{bev_box, overlap};

/// Philox4x32-10 of the counter `c` under `key` (`engine_common.cuh`'s `philox`).
fn philox(mut c: [u32; 4], key: [u32; 2]) -> [u32; 4] {
    let (mut k0, mut k1) = (key[0], key[1]);
    for _ in 0..10 {
        let p0 = u64::from(0xD251_1F53u32) * u64::from(c[0]);
        let p1 = u64::from(0xCD9E_8D57u32) * u64::from(c[2]);
        let (hi0, lo0) = ((p0 >> 32) as u32, p0 as u32);
        let (hi1, lo1) = ((p1 >> 32) as u32, p1 as u32);
        c = [hi1 ^ c[1] ^ k0, lo1, hi0 ^ c[3] ^ k1, lo0];
        k0 = k0.wrapping_add(0x9E37_79B9);
        k1 = k1.wrapping_add(0xBB67_AE85);
    }
    c
}

/// A uniform number in [0, 1) for (scene, position, frame, purpose) (`engine_common.cuh`'s `uniform`).
pub(super) fn uniform(key: [u32; 2], scene: u32, position: u32, frame: u32, purpose: u32) -> f64 {
    let r = philox([scene, position, frame, purpose], key);
    (f64::from(r[0] >> 5) * 67_108_864.0 + f64::from(r[1] >> 6)) * (1.0 / 9_007_199_254_740_992.0)
}

/// Whether (va, ia) ranks before (vb, ib): larger value, ties to the smaller id.
fn ranks_before(va: f32, ia: i32, vb: f32, ib: i32) -> bool {
    va > vb || (va == vb && ia < ib)
}

/// Whether id `i` may be drawn at a position of rule `r` (run `g`) whose group starts with `first`.
fn allowed(r: &Rule, g: &GroupRun, first: i32, i: i32, limited: bool) -> bool {
    let below = !limited || i < r.limit;
    if r.gstart < 0 {
        return below;
    }
    if r.gj == 0 {
        return below && (i < g.values || i == g.pad);
    }
    if first == g.pad {
        return i == g.pad;
    }
    if r.gj + 1 == g.size {
        return i >= g.last_lo && i < g.last_hi;
    }
    i < g.values && below
}

/// One draw's context: the step's settings and the rule of its position.
struct Site<'a> {
    d: &'a Draw,
    rule: &'a Rule,
    run: &'a GroupRun,
    first: i32,
    scene: u32,
    position: u32,
    frame: u32,
}

/// A draw from `row` under the site's rule (`draw.cu`'s `draw_from`).
fn draw_from(site: &Site<'_>, row: &[f32], limited: bool, purpose: u32) -> i32 {
    let d = site.d;
    let ok = |id: usize| {
        let x = row[id];
        x.is_finite() && allowed(site.rule, site.run, site.first, id as i32, limited)
    };
    let unif = |extra: u32| uniform(d.key, site.scene, site.position, site.frame, purpose | extra);
    if d.top_k < 1 || d.top_k > DRAW_KMAX {
        let mut best: Option<(f32, i32)> = None;
        for id in (0..d.vocab).filter(|&i| ok(i)) {
            let u = unif(id as u32) + f64::powi(2.0, -54);
            let key = (f64::from(row[id]) / d.temperature - (-u.ln()).ln()) as f32;
            if best.is_none_or(|(v, i)| ranks_before(key, id as i32, v, i)) {
                best = Some((key, id as i32));
            }
        }
        return best.map_or(0, |(_, i)| i);
    }
    let mut cands: Vec<(f32, i32)> = (0..d.vocab)
        .filter(|&i| ok(i))
        .map(|i| (row[i], i as i32))
        .collect();
    cands.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    // A group's first position: pad at its untruncated share, drawn first; the values of the top-k list
    // share the rest (`draw.cu`'s `pad_share`).
    let present = site.rule.gstart >= 0 && site.rule.gj == 0 && d.top_k > 1;
    let pad_share = present.then(|| {
        let top = cands.first().map_or(f64::NEG_INFINITY, |c| f64::from(c.0));
        let e = |x: f32| ((f64::from(x) - top) / d.temperature).exp();
        let total: f64 = cands.iter().map(|c| e(c.0)).sum();
        let pad = cands.iter().find(|c| c.1 == site.run.pad).map_or(0.0, |c| e(c.0));
        if total > 0.0 { pad / total } else { 0.0 }
    });
    cands.truncate(d.top_k);
    if let Some(share) = pad_share {
        let any = !cands.is_empty();
        cands.retain(|c| c.1 != site.run.pad);
        if any && (cands.is_empty() || unif(0x00ff_fffe) < share) {
            return site.run.pad;
        }
    }
    let Some(&(top, _)) = cands.first() else {
        return 0;
    };
    let mut pr: Vec<f64> = cands
        .iter()
        .map(|(v, _)| ((f64::from(*v) - f64::from(top)) / d.temperature).exp())
        .collect();
    let total: f64 = pr.iter().sum();
    pr.iter_mut().for_each(|p| *p /= total);
    let keep = if d.top_p < 1.0 {
        crate::sampling::nucleus(&mut pr, d.top_p, d.top_p_rest)
    } else {
        pr.len()
    };
    let mut u = unif(0x00ff_ffff);
    for j in 0..keep {
        if u < pr[j] {
            return cands[j].1;
        }
        u -= pr[j];
    }
    cands[keep - 1].1
}

/// The decoding step's draw on the host.
pub(super) fn draw(x: &mut HostExec, d: &Draw) -> Result<(), ExecError> {
    let p = x.i32s(d.pos)[0] as usize;
    let state: Vec<u32> = match x.bufs.get(d.state.id as usize) {
        Some((_, Store::U32(v))) => v[d.state.at..d.state.at + 3].to_vec(),
        _ => return Err(ExecError::Invalid("draw: state".into())),
    };
    let (rule, run) = match (x.bufs.get(d.rules.id as usize), x.bufs.get(d.runs.id as usize)) {
        (Some((_, Store::Rules(r))), Some((_, Store::Runs(g)))) => {
            let rule = r[d.rules.at + p];
            let run = if rule.gstart >= 0 {
                g[d.runs.at + rule.grun as usize]
            } else {
                GroupRun::EMPTY
            };
            (rule, run)
        }
        _ => return Err(ExecError::Invalid("draw: rules".into())),
    };
    let bytes = |b: umgen_cuda::Buf, len: usize| match x.bufs.get(b.id as usize) {
        Some((_, Store::U8(v))) => v[b.at..b.at + len].to_vec(),
        _ => Vec::new(),
    };
    let (keep_on, newborn) = (bytes(d.keep_on, d.m * d.keeps), bytes(d.newborn, d.m * d.groups));
    let logits = x.f32s(d.logits)[..d.m * d.vocab].to_vec();
    let keep_logits = x.f32s(d.keep_logits)[..d.m * d.keep_cap].to_vec();
    let mut tok = x.i32s(d.tok)[..d.m * d.n].to_vec();
    let mut counts = [0u32; 2];
    let Store::F64(mut boxes) = x.take(d.boxes.id) else {
        return Err(ExecError::Invalid("draw: boxes".into()));
    };
    let mut nboxes = x.i32s(d.nboxes)[..d.m].to_vec();
    for b in 0..d.m {
        let row = &mut tok[b * d.n..(b + 1) * d.n];
        if rule.known == 0 {
            let first = if rule.gstart >= 0 && rule.gj > 0 {
                row[rule.gstart as usize]
            } else {
                -1
            };
            let site = Site {
                d,
                rule: &rule,
                run: &run,
                first,
                scene: state[2] + b as u32,
                position: p as u32,
                frame: state[0],
            };
            let mut id = draw_from(&site, &logits[b * d.vocab..(b + 1) * d.vocab], true, 0);
            let kept = rule.keep >= 0 && keep_on[b * d.keeps + rule.keep as usize] != 0;
            let emptied = rule.gstart >= 0 && rule.gj > 0 && first == run.pad;
            if kept && id == rule.keep_pad && !emptied {
                let at = b * state[1] as usize + rule.keep_off as usize;
                id = draw_from(&site, &keep_logits[at..at + d.vocab], false, 1 << 24);
            }
            row[p] = id;
        }
        if rule.finish != 0 {
            let start = rule.gstart as usize;
            if row[start] == run.pad {
                continue;
            }
            let born = newborn[b * d.groups + rule.gindex as usize] != 0;
            counts[0] += u32::from(born);
            let mut v = [0.0f64; 5];
            let decoded = (0..5).all(|f| {
                let id = row[start + run.field[f] as usize];
                let ok = id >= 0 && id < run.bins[f];
                if ok {
                    v[f] =
                        run.lo[f] + (f64::from(id) + 0.5) * (run.hi[f] - run.lo[f]) / f64::from(run.bins[f]);
                }
                ok
            });
            if !decoded {
                continue;
            }
            let agent = bev_box(v[0], v[1], v[2], v[3], v[4]);
            let mine = &mut boxes
                [d.boxes.at + b * d.box_cap * BOX_WORDS..d.boxes.at + (b + 1) * d.box_cap * BOX_WORDS];
            let nb = nboxes[b] as usize;
            let held = |mine: &[f64], q: usize| {
                let o = &mine[BOX_WORDS * q..BOX_WORDS * q + 5];
                bev_box(o[0], o[1], o[2], o[3], o[4])
            };
            // [5]: the group's size for a new agent (negated once emptied), 0 for the ego and old agents.
            let kept = |mine: &[f64], q: usize| mine[BOX_WORDS * q + 5] >= 0.0;
            let drop = born
                && ((0..nb).filter(|&q| kept(mine, q)).count() >= run.max_boxes as usize
                    || (0..nb).any(|q| kept(mine, q) && overlap(&held(mine, q), &agent)));
            if !born && run.boxes == 2 {
                for q in 0..nb {
                    let o = BOX_WORDS * q;
                    if mine[o + 5] <= 0.0 || !overlap(&held(mine, q), &agent) {
                        continue;
                    }
                    let (first, size) = (mine[o + 6] as usize, mine[o + 5] as usize);
                    row[first..first + size].fill(run.pad);
                    mine[o + 5] = -mine[o + 5];
                    counts[1] += 1;
                }
            }
            if drop {
                row[start..=p].fill(run.pad);
                counts[1] += 1;
            } else if nb < d.box_cap {
                let o = &mut mine[BOX_WORDS * nb..BOX_WORDS * (nb + 1)];
                o[..5].copy_from_slice(&v);
                o[5] = if born { (p + 1 - start) as f64 } else { 0.0 };
                o[6] = start as f64;
                nboxes[b] += 1;
            }
        }
    }
    x.put(d.boxes.id, Store::F64(boxes));
    let put_i32 = |x: &mut HostExec, b: umgen_cuda::Buf, v: &[i32]| {
        if let Some((_, Store::I32(s))) = x.bufs.get_mut(b.id as usize) {
            s[b.at..b.at + v.len()].copy_from_slice(v);
        }
    };
    put_i32(x, d.tok, &tok);
    put_i32(x, d.nboxes, &nboxes);
    put_i32(x, d.pos, &[p as i32 + 1]);
    if let Some((_, Store::U32(c))) = x.bufs.get_mut(d.counts.id as usize) {
        c[d.counts.at] += counts[0];
        c[d.counts.at + 1] += counts[1];
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn philox_matches_the_reference_vectors() {
        // Random123's known-answer test for Philox4x32-10: counter and key all zeros, and all ones.
        assert_eq!(
            philox([0; 4], [0, 0]),
            [0x6627_e8d5, 0xe169_c58d, 0xbc57_ac4c, 0x9b00_dbd8]
        );
        assert_eq!(
            philox([u32::MAX; 4], [u32::MAX, u32::MAX]),
            [0x408f_276d, 0x41c8_3b0e, 0xa20b_c7c6, 0x6d54_51fd]
        );
    }

    /// The settings of a draw over one row of 300 ids (no buffers: `draw_from` reads none).
    fn settings(top_k: usize, top_p: f64, top_p_rest: bool) -> Draw {
        let b = umgen_cuda::Buf { id: 0, at: 0 };
        Draw {
            logits: b,
            keep_logits: b,
            rules: b,
            runs: b,
            keep_on: b,
            newborn: b,
            tok: b,
            pos: b,
            done: b,
            counts: b,
            boxes: b,
            nboxes: b,
            state: b,
            temperature: 1.0,
            top_p,
            top_p_rest,
            m: 1,
            n: 4,
            vocab: 300,
            top_k,
            keeps: 1,
            groups: 1,
            box_cap: 1,
            keep_cap: 0,
            run_count: 1,
            key: [7, 9],
        }
    }

    /// Ids drawn from `row` at position 1 of scenes `0..n` under `rule` (run `run`).
    fn draws(d: &Draw, rule: &Rule, run: &GroupRun, row: &[f32], n: u32) -> Vec<i32> {
        (0..n)
            .map(|scene| {
                let site = Site {
                    d,
                    rule,
                    run,
                    first: -1,
                    scene,
                    position: 1,
                    frame: 5,
                };
                draw_from(&site, row, true, 0)
            })
            .collect()
    }

    /// A top-20 list of id 0 at 0.9 and 19 tied values at 1/190: a plain top-p of 0.8 keeps id 0 alone;
    /// with `top_p_rest` id 0 keeps its 0.9 and the rest's nucleus (0.08 of 0.1) takes ids 1..16; as
    /// `draw.cu`'s emulator case.
    #[test]
    fn the_rest_nucleus_keeps_the_most_likely_id_at_its_share() {
        let mut row = vec![f32::NEG_INFINITY; 300];
        row[1..200].iter_mut().for_each(|x| *x = 0.0);
        row[0] = 171.0f32.ln();
        let free = |d: &Draw, n| draws(d, &Rule::FREE, &GroupRun::EMPTY, &row, n);
        let plain = free(&settings(20, 0.8, false), 2_000);
        assert!(plain.iter().all(|&id| id == 0), "{plain:?}");
        let rest = free(&settings(20, 0.8, true), 20_000);
        assert!(rest.iter().all(|&id| (0..=16).contains(&id)), "{rest:?}");
        let lead = rest.iter().filter(|&&id| id == 0).count();
        assert!((lead as f64 / 20_000.0 - 0.9).abs() < 0.01, "{lead}");
        // The 16 kept values share the rest about equally.
        let ones = rest.iter().filter(|&&id| id == 1).count() as f64 / 20_000.0;
        assert!((ones - 0.1 / 16.0).abs() < 0.003, "{ones}");
    }

    /// A group's first position with top-k 5: pad comes out at its untruncated share (0.9 here; 0.998 if
    /// the top-5 list alone counted), the values only from the list; as `draw.cu`'s emulator case.
    #[test]
    fn a_group_first_draw_keeps_pad_at_its_untruncated_share() {
        let d = settings(5, 1.0, false);
        let rule = Rule {
            gstart: 1,
            ..Rule::FREE
        };
        let run = GroupRun {
            size: 11,
            pad: 290,
            values: 256,
            last_lo: 256,
            last_hi: 260,
            ..GroupRun::EMPTY
        };
        let mut row = vec![f32::NEG_INFINITY; 300];
        row[..200].iter_mut().for_each(|x| *x = 0.0);
        row[290] = (9.0f32 * 200.0).ln();
        let n = 20_000u32;
        let mut pads = 0;
        for id in draws(&d, &rule, &run, &row, n) {
            match id {
                290 => pads += 1,
                id => assert!((0..4).contains(&id), "{id} is not in the top-5 list"),
            }
        }
        assert!((f64::from(pads) / f64::from(n) - 0.9).abs() < 0.01, "{pads}");
    }

    #[test]
    fn uniforms_cover_the_unit_interval_evenly() {
        let n = 100_000;
        let mut bins = [0usize; 10];
        for i in 0..n {
            let u = uniform([7, 9], i, 3, 1, 0);
            assert!((0.0..1.0).contains(&u));
            bins[(u * 10.0) as usize] += 1;
        }
        for b in bins {
            assert!((b as f64 / n as f64 - 0.1).abs() < 0.005, "{bins:?}");
        }
    }
}
