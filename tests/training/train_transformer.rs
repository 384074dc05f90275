//! A small transformer trained end to end on the GPU: linear embedding, a pre-norm block of
//! segment self-attention and a SwiGLU feed-forward, a linear head; MSE loss; AdamW with the
//! noam schedule and global-norm clipping, all parameters in one parameter store. The toy task
//! needs attention: each token's target mixes a mean over its own segment with a map of its
//! own features, on a fresh batch every step. With attention the loss must fall far below
//! what a token alone can know; without it (the control) it must not.

use crate::common;
use common::*;
use velox::engine::ops::adamw::AdamWConfig;
use velox::engine::ops::attention::Segments;
use velox::engine::ops::binary::{binary, Binary};
use velox::engine::Recorder;
use velox::models::layers::attention::MultiHeadAttention;
use velox::models::layers::{Linear, Loss, Param, RmsNorm, SwiGlu};
use velox::models::params::{Init, ParamStore};
use velox::models::schedule::noam;

const IN: usize = 6;
const WIDTH: usize = 32;
const HEADS: usize = 2;
const OUT: usize = 4;

struct Toy {
    embed: Linear,
    norm1: RmsNorm,
    attn: MultiHeadAttention,
    norm2: RmsNorm,
    ffn: SwiGlu,
    norm3: RmsNorm,
    head: Linear,
}

fn build(gpu: &Gpu) -> (ParamStore, Toy) {
    let mut b = ParamStore::builder();
    let lin = |b: &mut velox::models::params::ParamBuilder, name: &str, i: usize, o: usize| {
        b.add(&format!("{name}.w"), &[i, o], Init::Xavier).unwrap();
    };
    lin(&mut b, "embed", IN, WIDTH);
    b.add("embed.b", &[WIDTH], Init::Zeros).unwrap();
    for n in ["norm1", "norm2", "norm3"] {
        b.add(&format!("{n}.w"), &[WIDTH], Init::Ones).unwrap();
    }
    for n in ["q", "k", "v", "o"] {
        lin(&mut b, n, WIDTH, WIDTH);
    }
    lin(&mut b, "ffn.w1", WIDTH, 2 * WIDTH);
    lin(&mut b, "ffn.w3", WIDTH, 2 * WIDTH);
    lin(&mut b, "ffn.w2", 2 * WIDTH, WIDTH);
    lin(&mut b, "head", WIDTH, OUT);
    b.add("head.b", &[OUT], Init::Zeros).unwrap();
    let store = b.build(gpu, 1).unwrap();
    let p = |name: &str| {
        Param::from_tensors(store.param(name).unwrap().clone(), store.grad(name).unwrap().clone()).unwrap()
    };
    let linear = |w: &str| Linear::new(p(w), None).unwrap();
    let toy = Toy {
        embed: Linear::new(p("embed.w"), Some(p("embed.b"))).unwrap(),
        norm1: RmsNorm::new(p("norm1.w"), 1e-6).unwrap(),
        attn: MultiHeadAttention::new(linear("q.w"), linear("k.w"), linear("v.w"), linear("o.w"), HEADS)
            .unwrap(),
        norm2: RmsNorm::new(p("norm2.w"), 1e-6).unwrap(),
        ffn: SwiGlu::new(p("ffn.w1.w"), p("ffn.w3.w"), p("ffn.w2.w")).unwrap(),
        norm3: RmsNorm::new(p("norm3.w"), 1e-6).unwrap(),
        head: Linear::new(p("head.w"), Some(p("head.b"))).unwrap(),
    };
    (store, toy)
}

/// Records one training step's forward and backward; returns the loss tensor. Without
/// `attention` the block's attention branch is left out (the control: tokens then see only
/// themselves).
fn step(rec: &mut Recorder, m: &Toy, x: &Tensor, target: &Tensor, seg: &Segments, attention: bool) -> Tensor {
    let (h0, c_embed) = m.embed.forward(rec, x).unwrap();
    let (n1, c_n1) = m.norm1.forward(rec, &h0).unwrap();
    let (a, c_attn) = m.attn.forward(rec, &n1, None, seg).unwrap();
    let h1 = if attention { binary(rec, &h0, &a, Binary::Add).unwrap() } else { h0.clone() };
    let (n2, c_n2) = m.norm2.forward(rec, &h1).unwrap();
    let (f, c_ffn) = m.ffn.forward(rec, &n2).unwrap();
    let h2 = binary(rec, &h1, &f, Binary::Add).unwrap();
    let (n3, c_n3) = m.norm3.forward(rec, &h2).unwrap();
    let (y, c_head) = m.head.forward(rec, &n3).unwrap();
    let (loss, dy) = Loss::mse().forward_backward(rec, &y, target).unwrap();

    // Backward, in reverse; residual branches add their gradients.
    let dn3 = m.head.backward(rec, &c_head, &dy).unwrap();
    let dh2 = m.norm3.backward(rec, &c_n3, &dn3).unwrap();
    let dn2 = m.ffn.backward(rec, &c_ffn, &dh2).unwrap();
    let dh1_ffn = m.norm2.backward(rec, &c_n2, &dn2).unwrap();
    let dh1 = binary(rec, &dh2, &dh1_ffn, Binary::Add).unwrap();
    let dh0 = if attention {
        let (dn1, _) = m.attn.backward(rec, &c_attn, &dh1, seg).unwrap();
        let dh0_attn = m.norm1.backward(rec, &c_n1, &dn1).unwrap();
        binary(rec, &dh1, &dh0_attn, Binary::Add).unwrap()
    } else {
        dh1
    };
    m.embed.param_grads(rec, &c_embed, &dh0).unwrap();
    loss
}

/// A batch of the toy task: three segments of random features; each token's target is the
/// mean over its segment of x[.., :OUT] plus tanh of its own features.
fn batch(gpu: &Gpu, rng: &mut Rng, lens: &[usize]) -> (Tensor, Tensor) {
    let n: usize = lens.iter().sum();
    let x = rng.normal_vec(n * IN);
    let mut target = vec![0f32; n * OUT];
    let mut start = 0;
    for &l in lens {
        for o in 0..OUT {
            let mean = (start..start + l).map(|i| x[i * IN + o]).sum::<f32>() / l as f32;
            for i in start..start + l {
                target[i * OUT + o] = mean + 0.5 * (x[i * IN + o + 1] - x[i * IN + o]).tanh();
            }
        }
        start += l;
    }
    (Tensor::from_slice(gpu, &[n, IN], &x).unwrap(), Tensor::from_slice(gpu, &[n, OUT], &target).unwrap())
}

/// The toy task trained with the attention branch on or off, a fresh batch every step (so
/// that no network can learn the answers by heart): the losses of every step.
fn train(gpu: &Gpu, attention: bool) -> Vec<f32> {
    let mut rng = Rng::new(3);
    let lens = [16usize, 11, 21];
    let seg = Segments::from_lengths(gpu, &lens, &lens).unwrap();
    let (mut store, toy) = build(gpu);
    let cfg = AdamWConfig { weight_decay: 0.0, ..Default::default() };
    let mut losses = Vec::new();
    for s in 1..=STEPS {
        let (tx, tt) = batch(gpu, &mut rng, &lens);
        let mut rec = gpu.recorder().unwrap();
        store.zero_grads(&mut rec).unwrap();
        let loss = step(&mut rec, &toy, &tx, &tt, &seg, attention);
        store.adamw_step(&mut rec, &cfg, noam(1e-2, 20, s), Some(1.0)).unwrap();
        rec.submit().unwrap();
        store.grad_norm().unwrap();
        let l = loss.read::<f32>().unwrap()[0];
        assert!(l.is_finite(), "loss {l} at step {s}");
        losses.push(l);
    }
    losses
}

const STEPS: u64 = 800;

/// On batches it has never seen, the loss falls far with attention; without it (the control)
/// it stays near what a token alone can know (its segment's mean is mostly the other tokens').
/// Would catch attention that does not mix the segment, or a task a per-token network could
/// learn alone (with one fixed batch, as this test had, the control fell 48000x too).
#[test]
fn small_transformer_needs_its_attention() {
    let gpu = gpu();
    let mean = |l: &[f32]| l.iter().map(|&v| v as f64).sum::<f64>() / l.len() as f64;
    let on = train(&gpu, true);
    let off = train(&gpu, false);
    let (first, last) = (mean(&on[..10]), mean(&on[on.len() - 20..]));
    let (first_off, last_off) = (mean(&off[..10]), mean(&off[off.len() - 20..]));
    if verbose() {
        eprintln!(
            "toy transformer, {STEPS} steps (means of the first 10 and last 20): {first:.4e} -> {last:.4e} \
             ({:.0}x); without attention {first_off:.4e} -> {last_off:.4e} ({:.0}x)",
            first / last,
            first_off / last_off
        );
    }
    // What a token alone cannot know: of its segment's mean (of l unit normals) all but its own
    // share, variance (l - 1) / l^2 per channel; the tanh term is its own. The mean over tokens
    // of that is the best a network without attention can reach.
    let lens = [16.0f64, 11.0, 21.0];
    let floor = lens.iter().map(|l| l * (l - 1.0) / (l * l)).sum::<f64>() / lens.iter().sum::<f64>();
    // Measured on lavapipe: 1.19 -> 9.3e-3 with attention, 1.50 -> 6.4e-2 without (floor 5.8e-2).
    assert!(last < 0.25 * floor, "with attention the loss fell from {first} to {last} (floor {floor})");
    assert!(last_off > 0.9 * floor, "without attention the loss fell to {last_off}, below {floor}");
}
