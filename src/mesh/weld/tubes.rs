//! Tubes for [`weld`](super::weld): rims ordered by angle about a bridge's axis, the rings
//! between them and the faces zipping them (step 5 of the construction).

use super::*;

/// A boundary ring ordered for the tube, with the angle fraction of each vertex about the
/// bridge's axis (`len + 1` increasing values, the last one the first plus 1).
pub(super) type Ring = (Vec<u32>, Vec<f64>);

/// The bridge chosen at one contact.
pub(super) struct Bridge {
    pub(super) c: Cand,
    /// Faces of the two discs.
    pub(super) faces: [Vec<u32>; 2],
    /// The rings around `c.p` (traversed forward by the tube) and `c.q` (backward).
    pub(super) rings: [Ring; 2],
}

/// `ring` rotated to start at its smallest angle about the axis through `centre` along `axis`
/// (in a right-handed frame, times `sign`, as a fraction of a turn in `[0, 1)`), with its angle
/// fractions (running maximum of the unwrapped angle); `None` unless the ring winds exactly once
/// around the axis in the positive sense (the one that makes the tube face outwards), turning
/// backwards by at most [`MAX_BACKTURN`] in total.
pub(super) fn angle_params(
    pts: &[[f64; 3]],
    ring: &[u32],
    centre: [f64; 3],
    axis: [f64; 3],
    sign: f64,
) -> Option<Ring> {
    use std::f64::consts::{PI, TAU};
    let helper = if axis[0].abs() < 0.6 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = cross(axis, helper);
    let u = u.map(|x| x / norm(u));
    let v = cross(axis, u);
    let ang: Vec<f64> = ring
        .iter()
        .map(|&i| {
            let d = sub(pts[i as usize], centre);
            (sign * dot(d, v)).atan2(dot(d, u)).rem_euclid(TAU)
        })
        .collect();
    let k = ring.len();
    let start = (0..k).min_by(|&a, &b| ang[a].total_cmp(&ang[b]))?;
    let rotated: Vec<u32> = (0..k).map(|i| ring[(start + i) % k]).collect();
    let (mut unwrapped, mut back) = (ang[start], 0.0);
    let mut fr = vec![unwrapped / TAU];
    for i in 1..=k {
        let step = (ang[(start + i) % k] - ang[(start + i - 1) % k] + PI).rem_euclid(TAU) - PI;
        unwrapped += step;
        back -= step.min(0.0);
        fr.push(fr[i - 1].max(unwrapped / TAU));
    }
    if (unwrapped - ang[start] - TAU).abs() > 1e-6 || back > MAX_BACKTURN * TAU {
        return None;
    }
    fr[k] = fr[0] + 1.0;
    Some((rotated, fr))
}

/// The point at angle fraction `t ∈ [0, 1)` of the ring `(ring, fr)`, linear along its edges.
fn point_at(pos: &[[f64; 3]], (ring, fr): (&[u32], &[f64]), t: f64) -> [f64; 3] {
    let k = ring.len();
    let t = if t < fr[0] { t + 1.0 } else { t };
    let i = fr.partition_point(|&x| x <= t).clamp(1, k) - 1;
    let span = fr[i + 1] - fr[i];
    let w = if span > 0.0 {
        ((t - fr[i]) / span).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let (a, b) = (pos[ring[i] as usize], pos[ring[(i + 1) % k] as usize]);
    [0, 1, 2].map(|j| a[j] + w * (b[j] - a[j]))
}

/// Zips the rings `lower` (traversed forward by the new faces) and `upper` (traversed backward)
/// by increasing angle fraction.
fn zip((lower, fl): (&[u32], &[f64]), (upper, fu): (&[u32], &[f64]), faces: &mut Vec<[u32; 3]>) {
    let (m, n) = (lower.len(), upper.len());
    let (mut i, mut j) = (0usize, 0usize);
    while i < m || j < n {
        if j == n || (i < m && fl[i + 1] <= fu[j + 1]) {
            faces.push([lower[i], lower[(i + 1) % m], upper[j % n]]);
            i += 1;
        } else {
            faces.push([lower[i % m], upper[(j + 1) % n], upper[j]]);
            j += 1;
        }
    }
}

/// Builds the tube from ring `p` (traversed forward) to ring `q` (traversed backward) along
/// `axis` (unit, from `p` to `q`), appending vertices to `pos` and faces to `faces`; returns the
/// number of interpolated rings. A ring vertex at angle fraction `t` and parameter `s ∈ (0, 1)`
/// lies on the cubic Hermite curve from `a = p(t)` to `b = q(t)` with both tangents
/// `((b − a) · axis) axis` (linear along the axis, easing in and out radially: the tube leaves
/// both rims along the axis), its distance from the axis through `centre` scaled by
/// `1 − (1 − NECK) · 4 s (1 − s)`.
pub(super) fn tube(
    pos: &mut Vec<[f64; 3]>,
    (pr, fp): (&[u32], &[f64]),
    (qr, fq): (&[u32], &[f64]),
    axis: [f64; 3],
    centre: [f64; 3],
    e: f64,
    faces: &mut Vec<[u32; 3]>,
) -> usize {
    let (m, n) = (pr.len(), qr.len());
    let longest = (0..m)
        .map(|i| norm(sub(point_at(pos, (qr, fq), fp[i]), pos[pr[i] as usize])))
        .fold(0.0, f64::max);
    let rings = ((longest / e).round() as usize)
        .saturating_sub(1)
        .min(MAX_RINGS);
    let mut chain: Vec<Ring> = vec![(pr.to_vec(), fp.to_vec())];
    for k in 1..=rings {
        let s = k as f64 / (rings + 1) as f64;
        let h01 = s * s * (3.0 - 2.0 * s);
        let ht = s * (1.0 - s) * (1.0 - 2.0 * s); // h10 + h11
        let nu = 1.0 - (1.0 - NECK) * 4.0 * s * (1.0 - s);
        let count = ((m as f64 + (n as f64 - m as f64) * s).round() as usize).max(3);
        let mut ring = Vec::with_capacity(count);
        for l in 0..count {
            let t = l as f64 / count as f64;
            let a = point_at(pos, (pr, fp), t);
            let b = point_at(pos, (qr, fq), t);
            let ab = sub(b, a);
            let along = dot(ab, axis);
            ring.push(pos.len() as u32);
            let x = [0, 1, 2].map(|j| a[j] + h01 * ab[j] + ht * along * axis[j]);
            let rel = sub(x, centre);
            let ax = dot(rel, axis);
            pos.push([0, 1, 2].map(|j| centre[j] + ax * axis[j] + nu * (rel[j] - ax * axis[j])));
        }
        let fr = (0..=count).map(|l| l as f64 / count as f64).collect();
        chain.push((ring, fr));
    }
    chain.push((qr.to_vec(), fq.to_vec()));
    for w in chain.windows(2) {
        zip((&w[0].0, &w[0].1), (&w[1].0, &w[1].1), faces);
    }
    rings
}
