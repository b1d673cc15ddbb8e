//! Exact projection of learned code probabilities onto the hardware constraints (DESIGN §4
//! and §6, deep sensing): the feasible code set of highest total log-probability.
//!
//! # Scores
//! `logits [N, C, L]` per subpixel `n`, choice `c` and mask `l`:
//! - with the tap constraint, `C = M` (+1 for the drain, last): one choice per subpixel and
//!   mask, scored `logits[n][c][l]` (log-probabilities, or logits: a per-`(n, l)` constant
//!   does not change the answer);
//! - without it, `C = M` independent bits, scored `logits[n][m][l]` when on and 0 when off
//!   (log-odds: the Bernoulli log-likelihood up to a constant).
//!
//! # Method
//! The code is cut into independent *units*: with the Hamming constraint the whole block
//! (the constraint couples every channel at each transition), else each subpixel (tap
//! constraint) or each channel. A unit is a sequence of joint states over its *atoms*
//! (subpixels with the tap constraint, else channels); an atom's state is its bit pattern
//! and the age of each channel's current run, capped at `W` (the window constraint only
//! asks whether a run that ends has lasted `W` masks). Every state of a feasible cyclic code
//! is reachable within `W` steps from a state whose ages are all `W`, so the atom's state
//! space is the closure of those. A transition changes a channel's bit only when its run is
//! `W` old, and the changed bits over the unit at one transition are at most `H`.
//!
//! The codes loop, so the problem is a best *cycle*: for a start state `s₀` (the state at
//! mask `L−1` of the previous loop) a Viterbi pass over the `L` masks must end in `s₀`. The
//! exact solver tries the start states in the order of an upper bound (the best path from
//! `s₀` that need not close, one backward pass) and stops when the bound falls below the
//! best cycle found: exact, and in practice a few passes. It runs when the unit's joint
//! state space (after merging atom states no pattern sequence can tell apart) has at most
//! [`EXACT_STATE_LIMIT`] states — e.g. 2×2 block, 4 taps, tap + H 2 + W 2: 8⁴ = 4096, solved
//! exactly in well under a second — and within [`EXACT_WORK_LIMIT`] edge relaxations.
//! Beyond either, a beam search ([`BEAM_WIDTH`] joint states per mask, from the start
//! state of the best constant pattern) runs instead; its cycles are checked and the best
//! constant code — always feasible: no switch breaks any constraint — is kept when it is
//! better or no beam path closes, so the answer is always feasible. When the per-entry
//! argmax code is feasible it is optimal and returned at once.

use crate::codes::{CodeShape, Codes, Constraints};
use crate::error::{invalid, Result, SensorError};
use ndarray::ArrayView3;
use std::collections::HashMap;

/// Largest joint state space of a unit solved exactly.
pub const EXACT_STATE_LIMIT: usize = 1 << 14;
/// Edge relaxations the exact search may spend on start states before it hands over to
/// the beam search (about a second on one core).
pub const EXACT_WORK_LIMIT: u64 = 400_000_000;
/// Joint states kept per mask by the beam search beyond [`EXACT_STATE_LIMIT`].
pub const BEAM_WIDTH: usize = 128;

/// How a projection was solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// The argmax code was feasible.
    Argmax,
    /// Every unit solved exactly.
    Exact,
    /// At least one unit by beam search (feasible, not proven optimal).
    Beam,
}

/// The projected codes with their score.
#[derive(Debug, Clone)]
pub struct Projection {
    pub codes: Codes,
    /// Total score ([`score`]) of the codes.
    pub score: f64,
    /// Score of the per-entry argmax code (an upper bound; equal when it is feasible).
    pub argmax_score: f64,
    pub method: Method,
}

/// Choices per subpixel in `logits`: `M` (+1 drain with the tap constraint).
pub fn choices(shape: &CodeShape, constraints: &Constraints) -> usize {
    shape.taps + usize::from(constraints.tap && shape.drain)
}

/// The score of `codes` under `logits [N, C, L]` (see the module doc).
pub fn score(codes: &Codes, logits: &ArrayView3<'_, f32>) -> f64 {
    let s = codes.shape();
    let mut total = 0.0;
    for n in 0..s.subpixels() {
        for l in 0..s.length {
            if codes.constraints.tap {
                match (0..s.taps).find(|&m| codes.get(n, m, l)) {
                    Some(m) => total += logits[(n, m, l)] as f64,
                    None if s.drain => total += logits[(n, s.taps, l)] as f64,
                    None => {}
                }
            } else {
                total += (0..s.taps).filter(|&m| codes.get(n, m, l)).map(|m| logits[(n, m, l)] as f64).sum::<f64>();
            }
        }
    }
    total
}

/// The feasible codes of `shape` under `constraints` with the highest [`score`].
///
/// # Shapes
/// - `logits`: `[N, C, L]`, `N = bh·bw`, `C` = [`choices`], `L` = the code length.
pub fn project(shape: CodeShape, clock_hz: f64, constraints: Constraints, logits: &ArrayView3<'_, f32>) -> Result<Projection> {
    let shape = shape.validate()?;
    let (n_sub, taps, len) = (shape.subpixels(), shape.taps, shape.length);
    let c = choices(&shape, &constraints);
    if logits.dim() != (n_sub, c, len) {
        return Err(SensorError::Shape {
            what: "code logits".into(),
            got: logits.shape().to_vec(),
            expected: format!("[N, C, L] = [{n_sub}, {c}, {len}]"),
        });
    }
    if let Some((i, v)) = logits.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(invalid("code logits", v, format!("finite values (entry {i})")));
    }
    let mut codes = Codes::zeros(shape, clock_hz, constraints)?;

    // the per-entry argmax: optimal whenever it is feasible
    let patterns = atom_patterns(&shape, &constraints);
    let atom_score = |atom: usize, l: usize, p: u8| -> f64 { pattern_score(&shape, &constraints, logits, atom, l, p) };
    let atoms_total = if constraints.tap { n_sub } else { n_sub * taps };
    let mut argmax_score = 0.0;
    for a in 0..atoms_total {
        for l in 0..len {
            let (best, s) =
                patterns
                    .iter()
                    .map(|&p| (p, atom_score(a, l, p)))
                    .fold((0u8, f64::NEG_INFINITY), |acc, x| if x.1 > acc.1 { x } else { acc });
            argmax_score += s;
            set_atom(&mut codes, &constraints, a, l, best);
        }
    }
    if codes.violations().is_empty() {
        return Ok(Projection { score: score(&codes, logits), codes, argmax_score, method: Method::Argmax });
    }

    // independent units of atoms
    let units: Vec<Vec<usize>> =
        if constraints.hamming.is_some() { vec![(0..atoms_total).collect()] } else { (0..atoms_total).map(|a| vec![a]).collect() };
    let space = AtomSpace::new(&patterns, constraints.window.unwrap_or(1), if constraints.tap { taps } else { 1 });
    let budget = constraints.hamming.unwrap_or(usize::MAX);
    let mut method = Method::Exact;
    for unit in &units {
        let sc = |i: usize, l: usize, state: u32| atom_score(unit[i], l, space.pattern(state));
        let path = match solve_exact(&space, unit.len(), len, budget, &sc) {
            Exact::Done(p) => p,
            Exact::OutOfWork(found) => {
                method = Method::Beam;
                let beam = solve_beam(&space, unit.len(), len, budget, constraints.window.unwrap_or(1), &sc);
                match found {
                    Some(f) if path_score(&f, &sc) > path_score(&beam, &sc) => f,
                    _ => beam,
                }
            }
            Exact::TooLarge => {
                method = Method::Beam;
                solve_beam(&space, unit.len(), len, budget, constraints.window.unwrap_or(1), &sc)
            }
        };
        for (l, states) in path.iter().enumerate() {
            for (i, &s) in states.iter().enumerate() {
                set_atom(&mut codes, &constraints, unit[i], l, space.pattern(s));
            }
        }
    }
    codes.ensure_feasible()?;
    Ok(Projection { score: score(&codes, logits), codes, argmax_score, method })
}

/// The bit patterns an atom may take: one-hot taps (and all-off with a drain) for a subpixel
/// under the tap constraint, else 0 and 1 for a channel.
fn atom_patterns(shape: &CodeShape, constraints: &Constraints) -> Vec<u8> {
    if constraints.tap {
        let mut p: Vec<u8> = (0..shape.taps).map(|m| 1u8 << m).collect();
        if shape.drain {
            p.push(0);
        }
        p
    } else {
        vec![0, 1]
    }
}

fn pattern_score(shape: &CodeShape, constraints: &Constraints, logits: &ArrayView3<'_, f32>, atom: usize, l: usize, p: u8) -> f64 {
    if constraints.tap {
        let c = if p == 0 { shape.taps } else { p.trailing_zeros() as usize };
        logits[(atom, c, l)] as f64
    } else if p == 1 {
        logits[(atom / shape.taps, atom % shape.taps, l)] as f64
    } else {
        0.0
    }
}

fn set_atom(codes: &mut Codes, constraints: &Constraints, atom: usize, l: usize, p: u8) {
    let taps = codes.taps();
    if constraints.tap {
        for m in 0..taps {
            codes.set(atom, m, l, p >> m & 1 == 1);
        }
    } else {
        codes.set(atom / taps, atom % taps, l, p == 1);
    }
}

/// The reachable states of one atom: bit pattern and each channel's run age (capped at `W`),
/// with their successors and the bits each transition changes.
struct AtomSpace {
    /// `(pattern, ages)` per state.
    states: Vec<(u8, Vec<u8>)>,
    /// `(next state, changed bits)` per state.
    succ: Vec<Vec<(u32, u32)>>,
    /// The state of each pattern whose runs are all `W` old.
    settled: HashMap<u8, u32>,
}

impl AtomSpace {
    fn new(patterns: &[u8], w: usize, bits: usize) -> Self {
        let w = w.max(1) as u8;
        let mut ids: HashMap<(u8, Vec<u8>), u32> = HashMap::new();
        let mut states: Vec<(u8, Vec<u8>)> = Vec::new();
        let mut queue = Vec::new();
        let mut settled = HashMap::new();
        for &p in patterns {
            let s = (p, vec![w; bits]);
            let id = states.len() as u32;
            ids.insert(s.clone(), id);
            states.push(s);
            settled.insert(p, id);
            queue.push(id);
        }
        let mut succ: Vec<Vec<(u32, u32)>> = Vec::new();
        let mut head = 0;
        while head < queue.len() {
            let id = queue[head];
            head += 1;
            let (p, ages) = states[id as usize].clone();
            let mut out = Vec::new();
            'next: for &q in patterns {
                let mut next_ages = Vec::with_capacity(bits);
                for m in 0..bits {
                    if (p ^ q) >> m & 1 == 1 {
                        if ages[m] < w {
                            continue 'next; // the run that would end is shorter than W
                        }
                        next_ages.push(1);
                    } else {
                        next_ages.push((ages[m] + 1).min(w));
                    }
                }
                let key = (q, next_ages);
                let nid = match ids.get(&key) {
                    Some(&n) => n,
                    None => {
                        let n = states.len() as u32;
                        ids.insert(key.clone(), n);
                        states.push(key);
                        queue.push(n);
                        n
                    }
                };
                out.push((nid, (p ^ q).count_ones()));
            }
            if succ.len() <= id as usize {
                succ.resize(id as usize + 1, Vec::new());
            }
            succ[id as usize] = out;
        }
        succ.resize(states.len(), Vec::new());
        AtomSpace { states, succ, settled }.minimised()
    }

    /// Merge the states that no sequence of patterns can tell apart (Moore's partition
    /// refinement: same pattern, and for every next pattern an equivalent successor). An age
    /// that can never block a transition — e.g. the off-run of a tap under the tap constraint
    /// without drain, which always outlasts the run that ends before it — stops multiplying
    /// the joint state space: 2×2, 4 taps, tap + W 2 has 8 states per subpixel, not 32.
    fn minimised(self) -> Self {
        let n = self.states.len();
        let mut class: Vec<usize> = self.states.iter().map(|(p, _)| *p as usize).collect();
        let mut count = usize::MAX;
        loop {
            let mut ids: HashMap<(usize, Vec<(u8, usize)>), usize> = HashMap::new();
            let next: Vec<usize> = (0..n)
                .map(|s| {
                    let mut sig: Vec<(u8, usize)> = self.succ[s].iter().map(|&(t, _)| (self.pattern(t), class[t as usize])).collect();
                    sig.sort_unstable();
                    let key = (class[s], sig);
                    let k = ids.len();
                    *ids.entry(key).or_insert(k)
                })
                .collect();
            let new_count = ids.len();
            class = next;
            if new_count == count {
                break;
            }
            count = new_count;
        }
        let mut rep = vec![usize::MAX; count];
        for s in 0..n {
            if rep[class[s]] == usize::MAX {
                rep[class[s]] = s;
            }
        }
        let states = rep.iter().map(|&r| self.states[r].clone()).collect();
        let succ = rep
            .iter()
            .map(|&r| {
                let mut v: Vec<(u32, u32)> = self.succ[r].iter().map(|&(t, c)| (class[t as usize] as u32, c)).collect();
                v.sort_unstable();
                v.dedup();
                v
            })
            .collect();
        let settled = self.settled.iter().map(|(&p, &s)| (p, class[s as usize] as u32)).collect();
        AtomSpace { states, succ, settled }
    }

    fn len(&self) -> usize {
        self.states.len()
    }

    fn pattern(&self, s: u32) -> u8 {
        self.states[s as usize].0
    }
}

/// Joint successors of joint state `s` (mixed radix over the atoms' states) within `budget`
/// changed bits.
fn joint_successors(space: &AtomSpace, atoms: usize, s: usize, budget: usize, out: &mut Vec<u32>) {
    fn rec(space: &AtomSpace, digits: &[u32], a: usize, acc: usize, mult: usize, left: usize, out: &mut Vec<u32>) {
        if a == digits.len() {
            out.push(acc as u32);
            return;
        }
        for &(next, changed) in &space.succ[digits[a] as usize] {
            let changed = changed as usize;
            if changed <= left {
                rec(space, digits, a + 1, acc + next as usize * mult, mult * space.len(), left - changed, out);
            }
        }
    }
    let base = space.len();
    let mut digits = Vec::with_capacity(atoms);
    let mut r = s;
    for _ in 0..atoms {
        digits.push((r % base) as u32);
        r /= base;
    }
    out.clear();
    rec(space, &digits, 0, 0, 1, budget, out);
}

fn decode(space: &AtomSpace, atoms: usize, mut s: usize) -> Vec<u32> {
    (0..atoms)
        .map(|_| {
            let d = (s % space.len()) as u32;
            s /= space.len();
            d
        })
        .collect()
}

/// What the exact search gives.
enum Exact {
    /// The best cycle, as the atoms' states per mask.
    Done(Vec<Vec<u32>>),
    /// [`EXACT_WORK_LIMIT`] was spent before the bound proved a cycle best; the best cycle so
    /// far, if any.
    OutOfWork(Option<Vec<Vec<u32>>>),
    /// The joint state space exceeds [`EXACT_STATE_LIMIT`].
    TooLarge,
}

fn path_score(path: &[Vec<u32>], score: &dyn Fn(usize, usize, u32) -> f64) -> f64 {
    path.iter().enumerate().map(|(l, st)| st.iter().enumerate().map(|(a, &x)| score(a, l, x)).sum::<f64>()).sum()
}

/// The best cycle exactly (see the module doc).
fn solve_exact(space: &AtomSpace, atoms: usize, len: usize, budget: usize, score: &dyn Fn(usize, usize, u32) -> f64) -> Exact {
    let Some(n_states) = (0..atoms).try_fold(1usize, |acc, _| acc.checked_mul(space.len())).filter(|&n| n <= EXACT_STATE_LIMIT) else {
        return Exact::TooLarge;
    };
    // successors of every joint state, and every state's score at every mask
    let mut succ: Vec<Vec<u32>> = Vec::with_capacity(n_states);
    let mut buf = Vec::new();
    for s in 0..n_states {
        joint_successors(space, atoms, s, budget, &mut buf);
        succ.push(buf.clone());
    }
    let sc: Vec<Vec<f64>> = (0..len)
        .map(|l| (0..n_states).map(|s| decode(space, atoms, s).iter().enumerate().map(|(a, &x)| score(a, l, x)).sum()).collect())
        .collect();
    // upper bound per start state: the best path over masks 0..L from it, closed or not
    let mut bound = vec![0.0f64; n_states];
    for l in (0..len).rev() {
        bound = (0..n_states)
            .map(|s| succ[s].iter().map(|&t| sc[l][t as usize] + bound[t as usize]).fold(f64::NEG_INFINITY, f64::max))
            .collect();
    }
    let mut order: Vec<usize> = (0..n_states).filter(|&s| bound[s].is_finite()).collect();
    order.sort_by(|&a, &b| bound[b].total_cmp(&bound[a]));

    let mut best: Option<(f64, Vec<usize>)> = None;
    let mut f = vec![f64::NEG_INFINITY; n_states];
    let mut g = vec![f64::NEG_INFINITY; n_states];
    let mut back = vec![vec![u32::MAX; n_states]; len];
    let edges: u64 = succ.iter().map(|v| v.len() as u64).sum::<u64>() * len as u64;
    let mut work = 0u64;
    let decode_path = |path: Vec<usize>| path.into_iter().map(|s| decode(space, atoms, s)).collect::<Vec<_>>();
    for &s0 in &order {
        if let Some((b, _)) = &best {
            if bound[s0] <= *b {
                break;
            }
        }
        work += edges;
        if work > EXACT_WORK_LIMIT {
            return Exact::OutOfWork(best.map(|(_, p)| decode_path(p)));
        }
        f.iter_mut().for_each(|v| *v = f64::NEG_INFINITY);
        for &t in &succ[s0] {
            let v = sc[0][t as usize];
            if v > f[t as usize] {
                f[t as usize] = v;
                back[0][t as usize] = s0 as u32;
            }
        }
        for l in 1..len {
            g.iter_mut().for_each(|v| *v = f64::NEG_INFINITY);
            for s in 0..n_states {
                if f[s] == f64::NEG_INFINITY {
                    continue;
                }
                for &t in &succ[s] {
                    let v = f[s] + sc[l][t as usize];
                    if v > g[t as usize] {
                        g[t as usize] = v;
                        back[l][t as usize] = s as u32;
                    }
                }
            }
            std::mem::swap(&mut f, &mut g);
        }
        let closed = f[s0];
        if closed.is_finite() && best.as_ref().is_none_or(|(b, _)| closed > *b) {
            let mut path = vec![0usize; len];
            path[len - 1] = s0;
            for l in (1..len).rev() {
                path[l - 1] = back[l][path[l]] as usize;
            }
            best = Some((closed, path));
        }
    }
    // a constant pattern always closes, so a best cycle exists
    let (_, path) = best.expect("a constant code is a feasible cycle");
    Exact::Done(decode_path(path))
}

/// Beam search over the masks from the settled state of every atom's best constant pattern;
/// the best closing path that is feasible, or the best constant code.
fn solve_beam(
    space: &AtomSpace,
    atoms: usize,
    len: usize,
    budget: usize,
    w: usize,
    score: &dyn Fn(usize, usize, u32) -> f64,
) -> Vec<Vec<u32>> {
    // the best constant code: each atom its pattern of highest total score
    let patterns: Vec<u8> = space.settled.keys().copied().collect();
    let constant: Vec<u32> = (0..atoms)
        .map(|a| {
            let (p, _) = patterns
                .iter()
                .map(|&p| (p, (0..len).map(|l| score(a, l, space.settled[&p])).sum::<f64>()))
                .fold((patterns[0], f64::NEG_INFINITY), |acc, x| if x.1 > acc.1 { x } else { acc });
            space.settled[&p]
        })
        .collect();
    let mut best_path: Vec<Vec<u32>> = vec![constant.clone(); len];
    let mut best = path_score(&best_path, score);

    // layers of (state, score, parent index)
    let mut layers: Vec<Vec<(Vec<u32>, f64, usize)>> = Vec::with_capacity(len);
    let mut frontier: Vec<(Vec<u32>, f64, usize)> = vec![(constant.clone(), 0.0, usize::MAX)];
    for l in 0..len {
        let mut next: HashMap<Vec<u32>, (f64, usize)> = HashMap::new();
        for (pi, (state, s, _)) in frontier.iter().enumerate() {
            for cand in beam_successors(space, state, budget, &|a, x| score(a, l, x)) {
                let v = s + cand.iter().enumerate().map(|(a, &x)| score(a, l, x)).sum::<f64>();
                let e = next.entry(cand).or_insert((f64::NEG_INFINITY, pi));
                if v > e.0 {
                    *e = (v, pi);
                }
            }
        }
        let mut items: Vec<(Vec<u32>, f64, usize)> = next.into_iter().map(|(k, (v, p))| (k, v, p)).collect();
        items.sort_by(|a, b| b.1.total_cmp(&a.1));
        items.truncate(BEAM_WIDTH);
        layers.push(frontier);
        frontier = items;
    }
    layers.push(frontier);
    // every final entry: rebuild its path, keep it if the cycle is feasible
    for i in 0..layers[len].len() {
        let mut path = vec![Vec::new(); len];
        let mut idx = i;
        for l in (0..len).rev() {
            let (state, _, parent) = &layers[l + 1][idx];
            path[l] = state.clone();
            idx = *parent;
        }
        let v = layers[len][i].1;
        if v > best && cycle_feasible(space, &path, budget, w) {
            best = v;
            best_path = path;
        }
    }
    best_path
}

/// Successors of a joint state for the beam: no bit changed, and combinations (distinct
/// atoms, within the budget) of the 8 best single-atom changes.
fn beam_successors(space: &AtomSpace, state: &[u32], budget: usize, score: &dyn Fn(usize, u32) -> f64) -> Vec<Vec<u32>> {
    let mut base = Vec::with_capacity(state.len());
    let mut singles: Vec<(f64, usize, u32, usize)> = Vec::new();
    for (a, &x) in state.iter().enumerate() {
        let stay = space.succ[x as usize].iter().find(|(_, c)| *c == 0).map(|&(n, _)| n);
        let Some(stay) = stay else { return Vec::new() };
        base.push(stay);
        let s0 = score(a, stay);
        for &(n, c) in &space.succ[x as usize] {
            if c > 0 && c as usize <= budget {
                singles.push((score(a, n) - s0, a, n, c as usize));
            }
        }
    }
    singles.sort_by(|p, q| q.0.total_cmp(&p.0));
    singles.truncate(8);
    let mut out = vec![base.clone()];
    // subsets of the best singles, distinct atoms, within the budget
    fn rec(
        singles: &[(f64, usize, u32, usize)],
        i: usize,
        cur: &mut Vec<u32>,
        used: &mut Vec<usize>,
        left: usize,
        out: &mut Vec<Vec<u32>>,
    ) {
        for j in i..singles.len() {
            let (_, a, n, c) = singles[j];
            if c <= left && !used.contains(&a) {
                let old = cur[a];
                cur[a] = n;
                used.push(a);
                out.push(cur.clone());
                rec(singles, j + 1, cur, used, left - c, out);
                used.pop();
                cur[a] = old;
            }
        }
    }
    let mut cur = base;
    rec(&singles, 0, &mut cur, &mut Vec::new(), budget, &mut out);
    out
}

/// Whether a unit's path (states per mask) is a feasible cycle: at most `budget` changed bits
/// at every transition, the wrap included, and every cyclic run at least `w` long.
fn cycle_feasible(space: &AtomSpace, path: &[Vec<u32>], budget: usize, w: usize) -> bool {
    let len = path.len();
    let atoms = path[0].len();
    let pat = |l: usize, a: usize| space.pattern(path[l][a]);
    for l in 0..len {
        let next = (l + 1) % len;
        let changed: u32 = (0..atoms).map(|a| (pat(l, a) ^ pat(next, a)).count_ones()).sum();
        if changed as usize > budget {
            return false;
        }
    }
    for a in 0..atoms {
        for m in 0..8 {
            let seq: Vec<u8> = (0..len).map(|l| pat(l, a) >> m & 1).collect();
            if crate::codes::cyclic_runs(&seq).iter().any(|r| r.len < w) {
                return false;
            }
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};

    fn shape(bh: usize, bw: usize, taps: usize, length: usize, drain: bool) -> CodeShape {
        CodeShape { bh, bw, taps, length, drain }
    }

    fn random_logits(s: &CodeShape, c: &Constraints, seed: u64) -> Array3<f32> {
        let mut rng = StdRng::seed_from_u64(seed);
        Array3::from_shape_fn((s.subpixels(), choices(s, c), s.length), |_| rng.random_range(-3.0f32..3.0))
    }

    /// Every constraint combination: tap on/off × H none/1/2/3 × W none/2/3.
    fn combinations() -> Vec<Constraints> {
        let mut v = Vec::new();
        for tap in [false, true] {
            for hamming in [None, Some(1), Some(2), Some(3)] {
                for window in [None, Some(2), Some(3)] {
                    v.push(Constraints { tap, hamming, window });
                }
            }
        }
        v
    }

    /// The best feasible code by enumerating every code of a tiny shape.
    fn brute_force(s: CodeShape, c: Constraints, logits: &Array3<f32>) -> f64 {
        let n = s.subpixels();
        let per_entry: Vec<u8> = atom_patterns(&s, &c);
        // entries: (subpixel, mask) with the tap constraint, else (channel, mask) bits
        let entries = if c.tap { n * s.length } else { n * s.taps * s.length };
        let k = per_entry.len();
        let total = k.pow(entries as u32);
        let mut codes = Codes::zeros(s, 607e6, c).unwrap();
        let mut best = f64::NEG_INFINITY;
        for mut idx in 0..total {
            for e in 0..entries {
                let p = per_entry[idx % k];
                idx /= k;
                let (atom, l) = (e / s.length, e % s.length);
                set_atom(&mut codes, &c, atom, l, p);
            }
            if codes.violations().is_empty() {
                best = best.max(score(&codes, &logits.view()));
            }
        }
        best
    }

    #[test]
    fn equals_brute_force_on_tiny_shapes() {
        let mut cases = 0;
        for c in combinations() {
            // tap constraint: a 1×2 block of 2 taps (2^16 codes); else 1×1 (2^16 codes)
            let s = if c.tap { shape(1, 2, 2, 8, false) } else { shape(1, 1, 2, 8, false) };
            for seed in 0..3 {
                let logits = random_logits(&s, &c, seed);
                let p = project(s, 607e6, c, &logits.view()).unwrap();
                assert!(p.codes.violations().is_empty());
                let bf = brute_force(s, c, &logits);
                assert!(
                    (p.score - bf).abs() < 1e-6,
                    "{} seed {seed}: projection {} vs brute force {bf} ({:?})",
                    c.label(),
                    p.score,
                    p.method
                );
                assert!(p.score <= p.argmax_score + 1e-9);
                cases += 1;
            }
        }
        // with a drain: 1×1 block, 3 taps + drain under the tap constraint (4^8 codes)
        for c in combinations().into_iter().filter(|c| c.tap) {
            let s = shape(1, 1, 3, 8, true);
            let logits = random_logits(&s, &c, 7);
            let p = project(s, 607e6, c, &logits.view()).unwrap();
            let bf = brute_force(s, c, &logits);
            assert!((p.score - bf).abs() < 1e-6, "drain {}: {} vs {bf}", c.label(), p.score);
            cases += 1;
        }
        assert_eq!(cases, 24 * 3 + 12);
    }

    #[test]
    fn feasible_for_random_logits_under_every_combination() {
        let shapes = [
            shape(1, 1, 1, 8, false),
            shape(2, 2, 4, 32, false),
            shape(2, 2, 4, 32, true),
            shape(1, 2, 8, 16, true),
            shape(4, 4, 2, 8, false),
            shape(2, 1, 3, 64, true),
            shape(4, 4, 8, 16, true),
        ];
        for s in shapes {
            for c in combinations() {
                let logits = random_logits(&s, &c, 11);
                let p = project(s, 607e6, c, &logits.view()).unwrap();
                assert!(p.codes.violations().is_empty(), "{s:?} {}: infeasible", c.label());
                assert!(p.score <= p.argmax_score + 1e-6);
                // no worse than the best constant code, which is always feasible
                let mut best_const = 0.0;
                let pats = atom_patterns(&s, &c);
                let atoms = if c.tap { s.subpixels() } else { s.subpixels() * s.taps };
                for a in 0..atoms {
                    best_const += pats
                        .iter()
                        .map(|&q| (0..s.length).map(|l| pattern_score(&s, &c, &logits.view(), a, l, q)).sum::<f64>())
                        .fold(f64::NEG_INFINITY, f64::max);
                }
                if c.hamming.is_some() || p.method != Method::Beam {
                    assert!(p.score >= best_const - 1e-6, "{s:?} {}: {} below the best constant code {best_const}", c.label(), p.score);
                }
            }
        }
    }

    #[test]
    fn a_feasible_argmax_is_returned_as_is() {
        let s = shape(2, 2, 4, 16, false);
        let c = Constraints { tap: true, hamming: Some(2), window: Some(2) };
        // logits that prefer a feasible random code by a wide margin
        let target = crate::generate::random_codes(s, 607e6, c, 5).unwrap();
        let mut logits = random_logits(&s, &c, 3);
        for n in 0..4 {
            for l in 0..16 {
                let m = (0..4).find(|&m| target.get(n, m, l)).unwrap();
                logits[(n, m, l)] += 10.0;
            }
        }
        let p = project(s, 607e6, c, &logits.view()).unwrap();
        assert_eq!(p.method, Method::Argmax);
        for n in 0..4 {
            for m in 0..4 {
                assert_eq!(p.codes.channel(n * 4 + m), target.channel(n * 4 + m));
            }
        }
        // the paper's setting with random logits is solved exactly (8⁴ joint states)
        let p = project(s, 607e6, c, &random_logits(&s, &c, 9).view()).unwrap();
        assert_eq!(p.method, Method::Exact);
    }

    #[test]
    fn bad_logits_are_refused() {
        let s = shape(2, 2, 4, 8, false);
        let c = Constraints { tap: true, hamming: None, window: None };
        assert!(project(s, 607e6, c, &Array3::<f32>::zeros((4, 5, 8)).view()).is_err());
        let mut l = Array3::<f32>::zeros((4, 4, 8));
        l[(1, 2, 3)] = f32::NAN;
        assert!(project(s, 607e6, c, &l.view()).is_err());
    }
}
