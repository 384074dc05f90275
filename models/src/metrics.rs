//! Reconstruction metrics (paper, Metrics): PSNR and SSIM on images, the symmetric Chamfer
//! distance on point clouds. Plain f64 loops on the host: evaluation sizes are small. Each
//! names the reference it follows; the tests below check PSNR and SSIM against values
//! scikit-image 0.26 computed on fixed images (the call is quoted there).

/// PSNR in dB of two images with values in [0, 1] (any layout, same length): `10 log10(1 /
/// MSE)`, as scikit-image's `peak_signal_noise_ratio(.., data_range=1)`. Identical images give
/// +Inf. Test: `psnr_and_ssim_equal_scikit_image`.
pub fn psnr(image: &[f32], reference: &[f32]) -> f64 {
    assert_eq!(image.len(), reference.len(), "psnr: sizes differ");
    let mse = image.iter().zip(reference).map(|(&a, &b)| (a as f64 - b as f64).powi(2)).sum::<f64>()
        / image.len().max(1) as f64;
    -10.0 * mse.log10()
}

/// SSIM (Wang et al. 2004) of two `[h, w, c]` images in [0, 1]: an 11 x 11 Gaussian window of
/// standard deviation 1.5, K1 = 0.01, K2 = 0.03, population (co)variances, valid positions
/// only, averaged over positions and channels: scikit-image's `structural_similarity(..,
/// gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1,
/// channel_axis=-1)`, the usual way papers compute it. Images smaller than the window use a
/// window of their size (scikit-image refuses them). Test: `psnr_and_ssim_equal_scikit_image`.
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
/// distance to the nearest point of `b`, plus the same from `b` to `a` (a sum of the two
/// directions, of squared distances). The paper gives "the symmetric Chamfer distance ...
/// calculated on 8000 points" without the form; its figures settle it: 36.36 x 10^-5 for its
/// autoencoder and an oracle (two samplings of the truth) of 3.11 x 10^-4, the size of the
/// squared spacing of 8000 points on an object in [-1, 1]^3, where plain distances would be
/// near 1e-2. The evaluation takes 8000 points of each cloud (`velox eval recon --points`),
/// and its floor is two disjoint 8000-point samples of the truth. Brute force. Test:
/// `chamfer_by_hand`.
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

    /// Two images every tool can make the same way: `a = ((7x + 13y + 5c) mod 17) / 16` and
    /// `b = f32(0.5 a + 0.5 ((3x + 5y + 11c) mod 13) / 12)`.
    fn images(h: usize, w: usize, c: usize) -> (Vec<f32>, Vec<f32>) {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let va = ((x * 7 + y * 13 + ch * 5) % 17) as f32 / 16.0;
                    let k = ((x * 3 + y * 5 + ch * 11) % 13) as f64;
                    a.push(va);
                    b.push((0.5 * va as f64 + 0.5 * (k / 12.0)) as f32);
                }
            }
        }
        (a, b)
    }

    /// Values from scikit-image 0.26 on the images above, converted from f32 to f64:
    /// `structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
    /// use_sample_covariance=False, data_range=1.0, channel_axis=-1)` and
    /// `peak_signal_noise_ratio(a, b, data_range=1.0)`. Would catch a wrong window, constant,
    /// data range, variance normalisation or border rule.
    #[test]
    fn psnr_and_ssim_equal_scikit_image() {
        let cases = [
            (16, 16, 3, 0.5874744051153534, 13.34187436508562),
            (12, 20, 3, 0.5740624041347461, 13.196090266647413),
            (11, 11, 1, 0.44439299620604944, 12.803724587459211),
        ];
        for (h, w, c, want_ssim, want_psnr) in cases {
            let (a, b) = images(h, w, c);
            let got = ssim(&a, &b, h, w, c);
            assert!((got - want_ssim).abs() < 1e-12, "ssim {h}x{w}x{c}: {got} against {want_ssim}");
            let got = psnr(&a, &b);
            assert!((got - want_psnr).abs() < 1e-12, "psnr {h}x{w}x{c}: {got} against {want_psnr}");
        }
    }

    #[test]
    fn psnr_and_ssim_on_known_cases() {
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
    }

    #[test]
    fn chamfer_by_hand() {
        let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let q = [[0.0, 0.0, 0.1]];
        // a -> b: (0.01 + 1.01) / 2; b -> a: 0.01 (squared distances, means, summed).
        assert!((chamfer(&p, &q) - (0.51 + 0.01)).abs() < 1e-6);
        assert_eq!(subsample(&p, 1), vec![[0.0, 0.0, 0.0]]);
    }
}
