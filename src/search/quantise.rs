//! The quantisation of a histogram's bin probabilities to the corpus's `u16` counts (see
//! [`super::corpus`]).

use super::corpus::{total_at, MAX_SHIFT, TOTAL};

/// Quantises `prob` (non-negative; normalised here) to counts summing to `TOTAL · 2^s` and
/// returns `s`: the largest exponent ≤ [`MAX_SHIFT`] for which every count fits in a `u16`.
/// Largest-remainder rounding (ties to the lower bin), except that a positive probability gets
/// at least one count (the excess is taken back, one count at a time, from the bins whose
/// remainder is smallest, never below one count). The counts move by less than `2 · bins` units
/// in all; all zeros (and `s = 0`) when the sum is not positive.
pub fn quantise(prob: &[f64], out: &mut [u16]) -> u8 {
    let total: f64 = prob.iter().map(|p| p.max(0.0)).sum();
    if !(total > 0.0 && total.is_finite()) {
        out.iter_mut().for_each(|x| *x = 0);
        return 0;
    }
    let max_p = prob.iter().map(|p| p.max(0.0) / total).fold(0.0, f64::max);
    // Largest s with max_p · T_s + 2 ≤ 65 535 (a count may be rounded up by one, and a bin
    // rounded down may not be the largest).
    let mut shift = 0u8;
    while shift < MAX_SHIFT && max_p * total_at(shift + 1) + 2.0 <= u16::MAX as f64 {
        shift += 1;
    }
    let target = (TOTAL as u64) << shift;
    let t = target as f64;
    // Keeping every positive bin is possible (and the take-back below ends) while the positive
    // bins are at most half the total: always so below 2^15 bins.
    let positives = prob.iter().filter(|&&p| p > 0.0).count() as u64;
    let keep_positive = 2 * positives <= target;
    let mut frac: Vec<(f64, usize)> = Vec::with_capacity(prob.len());
    let mut sum = 0u64;
    for (b, (&p, o)) in prob.iter().zip(out.iter_mut()).enumerate() {
        let x = (p.max(0.0) / total * t).min(u16::MAX as f64);
        let mut f = x.floor();
        if keep_positive && p > 0.0 && f < 1.0 {
            f = 1.0;
        }
        *o = f as u16;
        sum += f as u64;
        frac.push((x - f, b));
    }
    // Remainders, largest first (ties by bin).
    frac.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    if sum < target {
        // One more count for the largest remainders (a bin of zero probability never gets one).
        let mut rem = target - sum;
        let positive: Vec<usize> = frac
            .iter()
            .filter(|&&(_, b)| prob[b] > 0.0)
            .map(|&(_, b)| b)
            .collect();
        for &b in positive.iter().cycle() {
            if rem == 0 {
                break;
            }
            if out[b] < u16::MAX {
                out[b] += 1;
                rem -= 1;
            }
        }
    } else if sum > target {
        // Forced ones took too much: take it back from the bins whose count exceeds their
        // share most (smallest remainder), never below one count.
        let mut excess = sum - target;
        for &(_, b) in frac.iter().rev().cycle() {
            if excess == 0 {
                break;
            }
            if out[b] > 1 {
                out[b] -= 1;
                excess -= 1;
            }
        }
    }
    shift
}
