//! A picture of one return leg: the true frames above each row's generated
//! ones, at evenly spaced times, on a trajectory chosen by a rule rather
//! than by eye.

use crate::probe::FrameScore;

/// The rule: of the trajectories with generated frames, the one whose mean
/// paired PSNR difference `a − b` is the median (the lower one of an even
/// count): a typical leg for the comparison, neither the best nor the worst.
/// `None` when no trajectory has frames.
pub fn median_trajectory(a: &[Vec<FrameScore>], b: &[Vec<FrameScore>]) -> Option<usize> {
    let mut means: Vec<(f64, usize)> = a
        .iter()
        .zip(b)
        .enumerate()
        .filter(|(_, (x, _))| !x.is_empty())
        .map(|(i, (x, y))| (x.iter().zip(y).map(|(p, q)| p.psnr - q.psnr).sum::<f64>() / x.len() as f64, i))
        .collect();
    means.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.cmp(&q.1)));
    means.get(means.len().saturating_sub(1) / 2).map(|m| m.1)
}

/// `count` indices evenly spread over `0..len`, the first and the last included.
pub fn spread(len: usize, count: usize) -> Vec<usize> {
    match (len, count) {
        (0, _) | (_, 0) => Vec::new(),
        (_, 1) => vec![0],
        _ => {
            let mut out: Vec<usize> = (0..count).map(|k| ((k * (len - 1)) as f64 / (count - 1) as f64).round() as usize).collect();
            out.dedup();
            out
        }
    }
}

/// Frames of `width`×`height` (RGB) in a grid, `rows[r][c]` at row r,
/// column c, with `gap` white pixels between them. Returns the picture's
/// width, height and pixels.
pub fn grid(rows: &[Vec<&[u8]>], width: usize, height: usize, gap: usize) -> (usize, usize, Vec<u8>) {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let span = |n: usize, size: usize| if n == 0 { 0 } else { n * (size + gap) - gap };
    let (w, h) = (span(columns, width), span(rows.len(), height));
    let mut out = vec![255u8; w * h * 3];
    for (r, row) in rows.iter().enumerate() {
        for (c, frame) in row.iter().enumerate() {
            assert_eq!(frame.len(), width * height * 3, "grid: a frame of another size");
            for y in 0..height {
                let to = ((r * (height + gap) + y) * w + c * (width + gap)) * 3;
                out[to..to + width * 3].copy_from_slice(&frame[y * width * 3..(y + 1) * width * 3]);
            }
        }
    }
    (w, h, out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leg(psnr: &[f64]) -> Vec<FrameScore> {
        psnr.iter().enumerate().map(|(t, &p)| FrameScore { t, psnr: p, ssim: 0.0, lpips: None, dreamsim: None, sharpness: None, psnr_in_warp: None, psnr_out_warp: None, sharpness_out_warp: None }).collect()
    }

    #[test]
    fn the_median_leg_is_neither_the_best_nor_the_worst() {
        let a = vec![leg(&[13.0, 13.0]), leg(&[10.0]), leg(&[]), leg(&[20.0, 18.0]), leg(&[11.0])];
        let b = vec![leg(&[10.0, 10.0]), leg(&[10.0]), leg(&[]), leg(&[10.0, 10.0]), leg(&[10.5])];
        // Mean differences: +3, 0, (no frames), +9, +0.5 → sorted 0, +0.5, +3, +9: the lower median is +0.5.
        assert_eq!(median_trajectory(&a, &b), Some(4));
        assert_eq!(median_trajectory(&a[..2], &b[..2]), Some(1));
        assert_eq!(median_trajectory(&[leg(&[])], &[leg(&[])]), None);
    }

    #[test]
    fn spread_covers_both_ends() {
        assert_eq!(spread(100, 4), [0, 33, 66, 99]);
        assert_eq!(spread(3, 5), [0, 1, 2]);
        assert_eq!(spread(7, 1), [0]);
        assert!(spread(0, 3).is_empty());
    }

    #[test]
    fn grid_places_each_frame_with_gaps() {
        let (a, b, c) = (vec![10u8; 2 * 2 * 3], vec![20u8; 12], vec![30u8; 12]);
        let (w, h, px) = grid(&[vec![&a, &b], vec![&c]], 2, 2, 1);
        assert_eq!((w, h), (5, 5));
        let at = |x: usize, y: usize| px[(y * w + x) * 3];
        assert_eq!([at(0, 0), at(1, 1), at(2, 0), at(3, 0), at(4, 1), at(0, 3), at(3, 3), at(1, 4)], [10, 10, 255, 20, 20, 30, 255, 30]);
    }
}
