//! Reconstruction metrics (paper, Metrics): PSNR and SSIM on images, the symmetric Chamfer
//! distance on point clouds. Plain f64 loops on the host: evaluation sizes are small.

/// PSNR in dB of two images with values in [0, 1] (any layout, same length). Identical images
/// give +Inf.
pub fn psnr(image: &[f32], reference: &[f32]) -> f64 {
    assert_eq!(image.len(), reference.len(), "psnr: sizes differ");
    let mse = image.iter().zip(reference).map(|(&a, &b)| (a as f64 - b as f64).powi(2)).sum::<f64>()
        / image.len().max(1) as f64;
    -10.0 * mse.log10()
}

/// SSIM (Wang et al. 2004) of two `[h, w, c]` images in [0, 1]: an 11 x 11 Gaussian window of
/// standard deviation 1.5, K1 = 0.01, K2 = 0.03, valid positions only, averaged over positions
/// and channels. Images smaller than the window use a window of their size.
pub fn ssim(image: &[f32], reference: &[f32], h: usize, w: usize, c: usize) -> f64 {
    assert_eq!(image.len(), h * w * c, "ssim: image size");
    assert_eq!(reference.len(), h * w * c, "ssim: reference size");
    let size = 11.min(h).min(w).max(1);
    let sigma = 1.5;
    let half = (size as f64 - 1.0) / 2.0;
    let g: Vec<f64> =
        (0..size).map(|i| (-((i as f64 - half).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
    let total: f64 = g.iter().sum::<f64>().powi(2);
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let mut sum = 0.0;
    let mut count = 0usize;
    for ch in 0..c {
        let px = |img: &[f32], y: usize, x: usize| img[(y * w + x) * c + ch] as f64;
        for y0 in 0..=h - size {
            for x0 in 0..=w - size {
                let (mut ma, mut mb, mut va, mut vb, mut cov) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for dy in 0..size {
                    for dx in 0..size {
                        let wgt = g[dy] * g[dx] / total;
                        let (a, b) = (px(image, y0 + dy, x0 + dx), px(reference, y0 + dy, x0 + dx));
                        ma += wgt * a;
                        mb += wgt * b;
                        va += wgt * a * a;
                        vb += wgt * b * b;
                        cov += wgt * a * b;
                    }
                }
                let (va, vb, cov) = (va - ma * ma, vb - mb * mb, cov - ma * mb);
                sum +=
                    ((2.0 * ma * mb + c1) * (2.0 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2));
                count += 1;
            }
        }
    }
    sum / count.max(1) as f64
}

/// Symmetric Chamfer distance of two point sets (xyz rows): the mean over `a` of the squared
/// distance to the nearest point of `b`, plus the same from `b` to `a`. Brute force.
pub fn chamfer(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::INFINITY;
    }
    let nearest = |p: &[f32; 3], set: &[[f32; 3]]| {
        set.iter()
            .map(|q| (0..3).map(|i| (p[i] as f64 - q[i] as f64).powi(2)).sum::<f64>())
            .fold(f64::INFINITY, f64::min)
    };
    let ab: f64 = a.iter().map(|p| nearest(p, b)).sum::<f64>() / a.len() as f64;
    let ba: f64 = b.iter().map(|p| nearest(p, a)).sum::<f64>() / b.len() as f64;
    ab + ba
}

/// `n` points of `points`, evenly strided (all of them when there are fewer): the evaluation's
/// 8000-point subsets, reproducible without a generator.
pub fn subsample(points: &[[f32; 3]], n: usize) -> Vec<[f32; 3]> {
    if points.len() <= n {
        return points.to_vec();
    }
    (0..n).map(|i| points[i * points.len() / n]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_ssim_and_chamfer_on_known_cases() {
        let a = vec![0.5f32; 16 * 16 * 3];
        let mut b = a.clone();
        b[0] = 0.6;
        // One pixel off by 0.1 (as f32 rounds it) in 768 values: mse = d^2 / 768.
        let d = 0.6f32 as f64 - 0.5f32 as f64;
        assert!((psnr(&b, &a) - 10.0 * (768.0 / (d * d)).log10()).abs() < 1e-9);
        assert_eq!(psnr(&a, &a), f64::INFINITY);
        assert!((ssim(&a, &a, 16, 16, 3) - 1.0).abs() < 1e-12);
        let noisy: Vec<f32> = (0..16 * 16 * 3).map(|i| if i % 2 == 0 { 0.0 } else { 1.0 }).collect();
        assert!(ssim(&noisy, &a, 16, 16, 3) < 0.1);
        let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let q = [[0.0, 0.0, 0.1]];
        // a -> b: (0.01 + 1.01) / 2; b -> a: 0.01.
        assert!((chamfer(&p, &q) - (0.51 + 0.01)).abs() < 1e-6);
        assert_eq!(subsample(&p, 1), vec![[0.0, 0.0, 0.0]]);
    }
}
