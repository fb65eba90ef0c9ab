//! The greedy choice of ring placements for the rigid-body errors: from a pool of places
//! (a ring stepped by its own diameter along lines in x, y and z at two levels of the other
//! axes, so each axis' translation and its rotations times their Abbe levers come apart), the
//! place that most reduces the predicted variance of the rigid-body terms is added, one at a
//! time, until the machine time is spent or no place is worth its time.
//!
//! Criterion (A-optimality on the normalised terms; Fedorov 1972, and the lazy evaluation of a
//! diminishing-returns gain, Minoux 1978): each place f gives the information
//! M_f = J_fᵀJ_f − J_fᵀN_f (N_fᵀN_f)⁺ N_fᵀJ_f of its scans (J_f the rows g·r of the
//! rigid-body terms, N_f its own placement columns, eliminated), additive over places. With
//! D = diag(Σ_pool M)^(−1/2) (each term in units of what the whole pool could tell of it) and
//! A = λI + Σ_chosen D·M_f·D, the gain of f is tr(A⁻¹) − tr((A + D·M_f·D)⁻¹)
//! = tr((I + UᵀA⁻¹U)⁻¹ UᵀA⁻²U), U·Uᵀ = D·M_f·D (Woodbury). A term nothing chosen sees yet
//! costs 1/λ: places that see a new term come first, then places that shrink the σ of the
//! terms already seen. The terms are the lab's spline variant of `rigid_body` (its most
//! demanding: the shape of every error between the knots), or the calibration's own
//! `rigid_body` when it has one; the other effects are taken as known (the groups before
//! determine them).
//!
//! Each place on a line along z is offered twice: with the first stylus alone, and with every
//! stylus and head angle as well (each other one once); the others with the first stylus
//! alone. An error of the z axis alone (its
//! straightness EXZ, EYZ and its rotations AXZ, AYZ, AZZ, functions of z) moves one stylus's
//! ring as a whole, which the placement takes; between styli it does not: a longer stylus
//! puts the ram Δz lower at the same ring (the straightness's slope times Δz) and a rotation
//! moves each ball by its own offset (δ = θ × o). Only the second kind of place sees them.
//! Since the two cost different machine time t_f, the criterion is the gain per second,
//! g_f / t_f (still diminishing, so the lazy evaluation holds); taking a place takes its twin.
//!
//! With [`ONE_WAY`] each stylus scans a place once, one way (the plan alternates the
//! direction from place to place, so the direction-dependent terms the other groups determine
//! stay balanced). The rigid-body signature of a place does not depend on the direction: a
//! second turn the other way halves the noise at a place the pool has already seen, where
//! another place sees the shape of each error between the knots. Both ways at every place
//! spent the budget on the first kind: with every stylus at the places along z as well, 16
//! minutes held 38 places and left the lines along x and y with 3–5 places each (machine 983:
//! held-out ring 1.60× the floor; 1.09× with one turn at each of 69 places in about the same
//! time).
//!
//! The criterion takes the model's other effects as known, so it can count a term as seen
//! by one stylus where, in the joint fit, the model's own effects take the same shape (the
//! x axis' yaw varying along x, `AZX c1`, on machine 131: neither a turn the other way nor a
//! second speed at every place determined it, every stylus along x did — between styli of
//! different offsets the yaw moves each ball by its own θ × o). The plan checks its
//! prediction: a term within reach left undetermined has its axis' lines scanned with every
//! stylus, and the places are chosen again (`plan`).

use super::*;
use nalgebra::{DMatrix, SymmetricEigen};

/// One place of the pool: where, and on which line.
#[derive(Debug, Clone)]
pub struct Place {
    /// Ring centre, machine axes, mm.
    pub center: Vec3,
    /// The line it lies on (e.g. `x at y 400, z -350`).
    pub line: String,
    /// Scanned with every stylus and head angle, not only the first (see the module).
    pub styli: bool,
}

/// What the greedy choice gives.
#[derive(Debug, Clone)]
pub struct Chosen {
    /// Indices into the pool, in the order chosen.
    pub order: Vec<usize>,
    /// Relative gain per second of each choice (the first is 1).
    pub gains: Vec<f64>,
    /// Normalised terms the pool could see, and those the chosen places see.
    pub terms_seen: (usize, usize),
}

/// Relative ridge λ of the criterion (a term unseen costs 1/λ).
const LAMBDA: f64 = 1e-3;
/// A place whose gain is below this share of the first choice's is not worth its time.
const MIN_GAIN: f64 = 2e-3;
/// Every `POOL_STRIDE`-th point of a scan for the criterion (a ring's rigid-body signature
/// is a few harmonics).
const POOL_STRIDE: usize = 48;

/// The scans of pool place `i`: the ring at 30 mm/s with `styli[0]` (the first tip, head
/// angle A1) once, in direction `dir` (+1 counter-clockwise); at a place with `styli` set,
/// once more with each other (tip, A1), the same way.
pub fn place_scans(i: usize, pl: &Place, styli: &[(u32, f64)], dir: i32, why: &str) -> Vec<Scan> {
    let mut v = vec![];
    let n = if pl.styli { styli.len() } else { 1 };
    for &(tip, a1) in styli.iter().take(n) {
        v.push(circle(i, 30.0, dir, 0.3, tip, a1, why));
    }
    if !ONE_WAY {
        if let Some(&(tip, a1)) = styli.first() {
            v.insert(1, circle(i, 30.0, -dir, 0.3, tip, a1, why));
        }
    }
    v
}

/// One turn per stylus at each place (see the module): the held-out ring of machine 983 went
/// 1.60 → 1.08× the floor with it (131 1.05 → 1.03×).
pub const ONE_WAY: bool = true;

/// The pool program: each place a ring of diameter `d` with its [`place_scans`].
pub fn pool_program(places: &[Place], d: f64, styli: &[(u32, f64)], why: &str) -> Program {
    let mut p = Program {
        name: "pool".into(),
        note: String::new(),
        features: vec![],
        scans: vec![],
        temperature: None,
    };
    for (i, pl) in places.iter().enumerate() {
        p.features.push(ring_at(pl.center, d));
        p.scans.extend(place_scans(
            i,
            pl,
            styli,
            if i % 2 == 0 { 1 } else { -1 },
            why,
        ));
    }
    p
}

/// Chooses places from `places` (see the module) within about `budget_s` of machine time
/// (each place's scans and a step's move; the caller orders them along their lines and
/// trims the last chosen if the moves made it longer). `styli`: the first (tip, A1) and the
/// others a place with `styli` set is scanned with.
#[allow(clippy::too_many_arguments)]
pub fn choose(
    cal: &Calibration,
    places: &[Place],
    d: f64,
    styli: &[(u32, f64)],
    budget_s: f64,
    a: &Assumptions,
    tip_r: &dyn Fn(u32) -> f64,
) -> Result<Chosen, LabError> {
    let pool = pool_program(places, d, styli, "");
    let ac = Assumptions {
        stride: POOL_STRIDE,
        heldout_alternate: false,
        ..a.clone()
    };
    let ds = ideal_dataset(cal, &pool, &ac)?;
    let cfg = match cal.effects.iter().find(|e| e.kind() == "rigid_body") {
        Some(c) => c.clone(),
        None => candidates::candidate("rigid_body:spline", &ds)?,
    };
    let mut sensors: SensorTable = ds.sensors.clone();
    let model = cfg
        .build(&mut sensors)
        .map_err(|e| LabError::Data(format!("rigid_body: {e}")))?
        .model;
    let k = model.n_params();
    let surfaces: Vec<Vec3> = ds.points.iter().map(|p| p.surface).collect();
    let all = vec![true; ds.points.len()];
    let art = fit_artifacts(&ds, &surfaces, &all);
    // Per place: its support (terms it sees) and its information there.
    let mut r = vec![Vec3::zeros(); k];
    let mut nu = vec![];
    let mut info: Vec<(Vec<usize>, DMatrix<f64>)> = vec![];
    for f in 0..places.len() {
        let pts: Vec<usize> = (0..ds.points.len())
            .filter(|i| ds.points[*i].feature == f && art.features[f].is_some())
            .collect();
        let mut rows: Vec<Vec<f64>> = vec![];
        let mut nrows: Vec<Vec<(usize, f64)>> = vec![];
        let mut touched = vec![false; k];
        let mut ncols: Vec<usize> = vec![];
        for &i in &pts {
            let p = &ds.points[i];
            model.regressors(&p.ctx, &mut r);
            let g = art.grad[i];
            let row: Vec<f64> = r
                .iter()
                .map(|x| {
                    let v = g.dot(x);
                    if v.is_finite() {
                        v
                    } else {
                        0.0
                    }
                })
                .collect();
            for (t, v) in touched.iter_mut().zip(&row) {
                *t |= *v != 0.0;
            }
            nuisance_row(&art, p, &p.surface, &mut nu);
            for (c, _) in &nu {
                if !ncols.contains(c) {
                    ncols.push(*c);
                }
            }
            rows.push(row);
            nrows.push(nu.clone());
        }
        let s: Vec<usize> = (0..k).filter(|j| touched[*j]).collect();
        let (ns, nn) = (s.len(), ncols.len());
        let mut jj = DMatrix::<f64>::zeros(ns, ns);
        let mut jn = DMatrix::<f64>::zeros(ns, nn);
        let mut cc = DMatrix::<f64>::zeros(nn, nn);
        for (row, nr) in rows.iter().zip(&nrows) {
            let x: Vec<f64> = s.iter().map(|j| row[*j]).collect();
            for a in 0..ns {
                if x[a] == 0.0 {
                    continue;
                }
                for b in 0..ns {
                    jj[(a, b)] += x[a] * x[b];
                }
            }
            for (c, v) in nr {
                let cl = ncols.iter().position(|q| q == c).unwrap_or(0);
                for a in 0..ns {
                    jn[(a, cl)] += x[a] * v;
                }
                for (c2, v2) in nr {
                    let cl2 = ncols.iter().position(|q| q == c2).unwrap_or(0);
                    cc[(cl, cl2)] += v * v2;
                }
            }
        }
        let m = if nn > 0 {
            let pinv = cc
                .pseudo_inverse(1e-12)
                .map_err(|e| LabError::Data(format!("pool place {f}: {e}")))?;
            &jj - &jn * pinv * jn.transpose()
        } else {
            jj
        };
        info.push((s, m));
    }
    // Normalisation by the pool's total.
    let mut diag = vec![0.0; k];
    for (s, m) in &info {
        for (a, j) in s.iter().enumerate() {
            diag[*j] += m[(a, a)].max(0.0);
        }
    }
    let top = diag.iter().cloned().fold(0.0, f64::max);
    let seen: Vec<bool> = diag.iter().map(|d| *d > 1e-12 * top && top > 0.0).collect();
    let idx: Vec<Option<usize>> = {
        let mut n = 0;
        seen.iter()
            .map(|s| {
                s.then(|| {
                    n += 1;
                    n - 1
                })
            })
            .collect()
    };
    let ke = seen.iter().filter(|s| **s).count();
    // Low-rank factors U_f (support in the seen terms' numbering, |S|×r).
    let mut factors: Vec<(Vec<usize>, DMatrix<f64>)> = vec![];
    for (s, m) in &info {
        let keep: Vec<usize> = (0..s.len()).filter(|a| seen[s[*a]]).collect();
        let sup: Vec<usize> = keep.iter().map(|a| idx[s[*a]].unwrap_or(0)).collect();
        let n = keep.len();
        let mut ms = DMatrix::<f64>::zeros(n, n);
        for (x, &a) in keep.iter().enumerate() {
            for (y, &b) in keep.iter().enumerate() {
                ms[(x, y)] = m[(a, b)] / (diag[s[a]] * diag[s[b]]).sqrt();
            }
        }
        let e = SymmetricEigen::new(ms);
        let lmax = e.eigenvalues.iter().cloned().fold(0.0, f64::max);
        let cols: Vec<usize> = (0..n)
            .filter(|c| e.eigenvalues[*c] > 1e-9 * lmax && lmax > 0.0)
            .collect();
        let mut u = DMatrix::<f64>::zeros(n, cols.len());
        for (q, &c) in cols.iter().enumerate() {
            let w = e.eigenvalues[c].sqrt();
            for x in 0..n {
                u[(x, q)] = e.eigenvectors[(x, c)] * w;
            }
        }
        factors.push((sup, u));
    }
    // Greedy with lazy re-evaluation: the gain of a place only falls as others are chosen.
    let mut ainv = DMatrix::<f64>::identity(ke, ke) / LAMBDA;
    let gain_of = |ainv: &DMatrix<f64>, f: usize| -> (f64, DMatrix<f64>, DMatrix<f64>) {
        let (sup, u) = &factors[f];
        let r = u.ncols();
        if r == 0 {
            return (0.0, DMatrix::zeros(ke, 0), DMatrix::zeros(0, 0));
        }
        // Z = A⁻¹[:, S]·U (ke×r); W = I + Uᵀ·A⁻¹[S, S]·U.
        let mut z = DMatrix::<f64>::zeros(ke, r);
        for (x, &j) in sup.iter().enumerate() {
            for q in 0..r {
                let v = u[(x, q)];
                if v != 0.0 {
                    for i in 0..ke {
                        z[(i, q)] += ainv[(i, j)] * v;
                    }
                }
            }
        }
        let mut w = DMatrix::<f64>::identity(r, r);
        for (x, &j) in sup.iter().enumerate() {
            for q in 0..r {
                for q2 in 0..r {
                    w[(q, q2)] += u[(x, q)] * z[(j, q2)];
                }
            }
        }
        let winv = w
            .clone()
            .try_inverse()
            .unwrap_or_else(|| DMatrix::zeros(r, r));
        let ztz = z.transpose() * &z;
        let g = (&winv * ztz).trace();
        (if g.is_finite() { g } else { 0.0 }, z, winv)
    };
    let mut bound: Vec<f64> = vec![f64::INFINITY; places.len()];
    let mut taken = vec![false; places.len()];
    let mut order = vec![];
    let mut gains = vec![];
    let mut first = None;
    // Machine time of each place: its scans, and the move from the last by about a step.
    let per_place: Vec<f64> = places
        .iter()
        .map(|pl| {
            let one = pool_program(std::slice::from_ref(pl), d, styli, "");
            machine_time_s(&one, tip_r) + d / MOVE_SPEED_MM_S + 0.3
        })
        .collect();
    let mut used = 0.0;
    loop {
        // The place with the largest bound on its gain per second, re-evaluated until it
        // stays on top.
        let pick = loop {
            let best = (0..places.len())
                .filter(|f| !taken[*f])
                .max_by(|a, b| bound[*a].total_cmp(&bound[*b]).then(b.cmp(a)));
            let Some(f) = best else { break None };
            let (g, z, winv) = gain_of(&ainv, f);
            bound[f] = g / per_place[f];
            let next = (0..places.len())
                .filter(|x| !taken[*x] && *x != f)
                .map(|x| bound[x])
                .fold(f64::NEG_INFINITY, f64::max);
            if bound[f] >= next {
                break Some((f, bound[f], z, winv));
            }
        };
        let Some((f, g, z, winv)) = pick else { break };
        let g0 = *first.get_or_insert(g);
        if !(g0 > 0.0) || g < MIN_GAIN * g0 {
            break;
        }
        // A place is taken once, with or without the other styli.
        for (x, pl) in places.iter().enumerate() {
            if (pl.center - places[f].center).norm() < 1.0 {
                taken[x] = true;
            }
        }
        if used + per_place[f] > budget_s {
            break;
        }
        used += per_place[f];
        ainv -= &z * winv * z.transpose();
        order.push(f);
        gains.push(g / g0);
    }
    let seen_chosen = {
        let mut v = vec![false; ke];
        for f in &order {
            for j in &factors[*f].0 {
                v[*j] = true;
            }
        }
        v.iter().filter(|x| **x).count()
    };
    Ok(Chosen {
        order,
        gains,
        terms_seen: (ke, seen_chosen),
    })
}
