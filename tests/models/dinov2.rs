//! DINOv2 on the engine against the `transformers` package's `Dinov2Model`: a small random
//! model made by `tools/dinov2_fixture.py` (weights under the published file's names, the
//! model's outputs computed in f64), at the trained position grid and at a larger non-square
//! grid whose positions are interpolated; the f16 path; the names `transformers` 5 writes;
//! bicubic resampling against a direct evaluation; bad files refused by name.

use crate::common;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::*;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use velox::engine::Precision;
use velox::models::velox::dinov2::{Dinov2, Dinov2Config, PATCH_VALUES};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dinov2").join(name)
}

/// Every f32 tensor of a safetensors file.
fn read(path: &Path) -> BTreeMap<String, (Vec<usize>, Vec<f32>)> {
    let bytes = std::fs::read(path).unwrap();
    let file = SafeTensors::deserialize(&bytes).unwrap();
    file.tensors()
        .into_iter()
        .map(|(k, t)| {
            assert_eq!(t.dtype(), Dtype::F32, "{k}");
            let v = t.data().chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
            (k, (t.shape().to_vec(), v))
        })
        .collect()
}

fn write(path: &Path, tensors: &BTreeMap<String, (Vec<usize>, Vec<f32>)>) {
    let bytes: BTreeMap<&String, Vec<u8>> =
        tensors.iter().map(|(k, (_, v))| (k, bytemuck::cast_slice(v).to_vec())).collect();
    let views: Vec<(&String, TensorView)> = tensors
        .iter()
        .map(|(k, (s, _))| (k, TensorView::new(Dtype::F32, s.clone(), &bytes[k]).unwrap()))
        .collect();
    std::fs::write(path, safetensors::serialize(views, None).unwrap()).unwrap();
}

/// The engine's output and the fixture's for one case.
fn run(model: &Dinov2, case: &str, precision: Precision) -> (Vec<f32>, Vec<f64>) {
    let cases = read(&fixture("cases.safetensors"));
    let (shape, pixels) = &cases[&format!("{case}.pixels")];
    let (n, h, w) = (shape[0], shape[2], shape[3]);
    let out = model.forward(&gpu(), pixels, n, h, w, precision).unwrap();
    let (hshape, hidden) = &cases[&format!("{case}.hidden")];
    assert_eq!(out.shape(), [hshape[0] * hshape[1], hshape[2]], "{case}");
    (out.read().unwrap(), f64s(hidden))
}

#[test]
fn matches_transformers_at_the_trained_grid_and_interpolated() {
    let model = Dinov2::load(&gpu(), &fixture("weights.safetensors")).unwrap();
    assert_eq!(model.config, Dinov2Config { width: 64, depth: 2, heads: 4, hidden: 256, grid: 4, eps: 1e-6 });
    // The file's hash, as the token store hashes checkpoints (a generator records it).
    let hash = velox::models::velox::tokens::checkpoint_hash(&fixture("weights.safetensors")).unwrap();
    assert_eq!(model.file_hash, Some(hash));
    for case in ["trained_grid", "interpolated"] {
        let (got, want) = run(&model, case, Precision::F32);
        assert_nmse(&format!("{case} f32"), &got, &want, 1e-8);
    }
    if gpu().caps().f16_storage {
        for case in ["trained_grid", "interpolated"] {
            let (got, want) = run(&model, case, Precision::F16);
            assert_nmse(&format!("{case} f16"), &got, &want, 1e-6);
        }
    }
}

/// `transformers` 5 saves the attention as `q_proj` .. `o_proj`, and some exports put every
/// name under `dinov2.`; both read as the published names do, to the same bits.
#[test]
fn reads_the_names_transformers_5_writes() {
    let dir = std::env::temp_dir().join(format!("velox-dinov2-names-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(fixture("config.json"), dir.join("config.json")).unwrap();
    let renamed: BTreeMap<String, _> = read(&fixture("weights.safetensors"))
        .into_iter()
        .map(|(k, v)| {
            let k = k
                .replace("attention.attention.query", "attention.q_proj")
                .replace("attention.attention.key", "attention.k_proj")
                .replace("attention.attention.value", "attention.v_proj")
                .replace("attention.output.dense", "attention.o_proj");
            (format!("dinov2.{k}"), v)
        })
        .collect();
    write(&dir.join("model.safetensors"), &renamed);
    let a = Dinov2::load(&gpu(), &fixture("weights.safetensors")).unwrap();
    let b = Dinov2::load(&gpu(), &dir.join("model.safetensors")).unwrap();
    assert_eq!(run(&a, "interpolated", Precision::F32).0, run(&b, "interpolated", Precision::F32).0);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The position table against a direct evaluation of the bicubic kernel at each output's
/// source coordinate: the separable sum, the border clamp and the identity at the same size.
#[test]
fn positions_resample_bicubically_as_pytorch_does() {
    let model = Dinov2::load(&gpu(), &fixture("weights.safetensors")).unwrap();
    let tensors = read(&fixture("weights.safetensors"));
    let pos = &tensors["embeddings.position_embeddings"].1;
    let bias = &tensors["embeddings.patch_embeddings.projection.bias"].1;
    let cls = &tensors["embeddings.cls_token"].1;
    let (d, g) = (64usize, 4usize);
    let kernel = |x: f64| {
        let (a, x) = (-0.75f64, x.abs());
        if x <= 1.0 {
            ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
        } else if x < 2.0 {
            ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
        } else {
            0.0
        }
    };
    for (gh, gw) in [(4, 4), (5, 7), (2, 3), (9, 4)] {
        let table = model.position_table(gh, gw);
        assert_eq!(table.len(), (1 + gh * gw) * d);
        for c in 0..d {
            assert!((table[c] as f64 - (cls[c] as f64 + pos[c] as f64)).abs() < 1e-6);
        }
        for oy in 0..gh {
            for ox in 0..gw {
                let sy = (oy as f64 + 0.5) * g as f64 / gh as f64 - 0.5;
                let sx = (ox as f64 + 0.5) * g as f64 / gw as f64 - 0.5;
                for c in (0..d).step_by(7) {
                    let mut v = 0.0;
                    for iy in sy.floor() as i64 - 1..=sy.floor() as i64 + 2 {
                        for ix in sx.floor() as i64 - 1..=sx.floor() as i64 + 2 {
                            let (y, x) =
                                (iy.clamp(0, g as i64 - 1) as usize, ix.clamp(0, g as i64 - 1) as usize);
                            v += kernel(sy - iy as f64)
                                * kernel(sx - ix as f64)
                                * pos[(1 + y * g + x) * d + c] as f64;
                        }
                    }
                    let got = table[(1 + oy * gw + ox) * d + c] as f64 - bias[c] as f64;
                    assert!((got - v).abs() < 1e-5, "grid {gh}x{gw} ({oy},{ox}) channel {c}: {got} vs {v}");
                    if (gh, gw) == (g, g) {
                        assert!((got - pos[(1 + oy * g + ox) * d + c] as f64).abs() < 1e-6);
                    }
                }
            }
        }
    }
}

#[test]
fn patch_rows_are_channel_major_with_a_zero_class_row() {
    let (h, w) = (28, 42);
    let pixels: Vec<f32> = (0..2 * 3 * h * w).map(|i| i as f32).collect();
    let rows = Dinov2::patch_rows(&pixels, 2, h, w).unwrap();
    let per_image = 1 + 2 * 3;
    assert_eq!(rows.len(), 2 * per_image * PATCH_VALUES);
    assert!(rows[..PATCH_VALUES].iter().all(|&v| v == 0.0));
    // Image 1, patch (1, 2), channel 2, pixel (3, 5) of the patch.
    let (f, py, px, c, ky, kx) = (1, 1, 2, 2, 3, 5);
    let row = (f * per_image + 1 + py * 3 + px) * PATCH_VALUES;
    let want = ((f * 3 + c) * h + py * 14 + ky) * w + px * 14 + kx;
    assert_eq!(rows[row + (c * 14 + ky) * 14 + kx], want as f32);
    assert!(Dinov2::patch_rows(&pixels, 2, 27, w).unwrap_err().to_string().contains("multiples of 14"));
    let mut nan = pixels.clone();
    nan[5] = f32::NAN;
    assert!(Dinov2::patch_rows(&nan, 2, h, w).unwrap_err().to_string().contains("not finite"));
}

#[test]
fn bad_weight_files_are_refused_by_name() {
    let dir = std::env::temp_dir().join(format!("velox-dinov2-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = read(&fixture("weights.safetensors"));
    let err = |tensors: &BTreeMap<String, (Vec<usize>, Vec<f32>)>| {
        write(&dir.join("w.safetensors"), tensors);
        Dinov2::load(&gpu(), &dir.join("w.safetensors")).err().expect("refused").to_string()
    };
    let mut missing = good.clone();
    missing.remove("encoder.layer.1.mlp.fc2.bias");
    assert!(err(&missing).contains("encoder.layer.1.mlp.fc2.bias"), "{}", err(&missing));
    let mut shaped = good.clone();
    shaped.get_mut("encoder.layer.0.norm2.weight").unwrap().0 = vec![2, 32];
    assert!(err(&shaped).contains("norm2.weight"));
    let mut nan = good.clone();
    nan.get_mut("layernorm.bias").unwrap().1[3] = f32::NAN;
    assert!(err(&nan).contains("non-finite"));
    let mut extra = good.clone();
    extra.insert("embeddings.register_tokens".into(), (vec![1, 4, 64], vec![0.0; 256]));
    assert!(err(&extra).contains("registers"));
    std::fs::write(dir.join("w.safetensors"), b"not a weight file").unwrap();
    assert!(Dinov2::load(&gpu(), &dir.join("w.safetensors"))
        .err()
        .unwrap()
        .to_string()
        .contains("safetensors"));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_large_config_has_the_published_parameter_count() {
    // facebook/dinov2-large: 304,368,640 parameters (mask token included).
    assert_eq!(Dinov2Config::large().num_parameters(), 304_368_640);
}
