//! Uploads and downloads through staging buffers, the path of every discrete GPU, forced on a
//! device whose memory is mapped (lavapipe) so that CI runs it: whole tensors, views at
//! offsets, empty tensors, and ops between them.

mod common;
use common::*;
use velox_engine::ops::binary::{binary, Binary};

/// The tests count the process's submissions: one at a time.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// A device that stages every transfer, and the hold that keeps this file's tests one at a time.
fn staged_device() -> (std::sync::MutexGuard<'static, ()>, Gpu) {
    let one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    std::env::set_var("VELOX_FORCE_STAGING", "1");
    (one, Gpu::new().unwrap())
}

#[test]
fn staging_round_trips_tensors_views_and_op_results() {
    let (_one, gpu) = staged_device();
    let mut rng = Rng::new(1);
    let staged = gpu.staged_bytes();
    for &n in &[0usize, 1, 3, 1000, 100_003] {
        let a = rng.normal_vec(n);
        let b = rng.normal_vec(n);
        let ta = Tensor::from_slice(&gpu, &[n], &a).unwrap();
        let tb = Tensor::from_slice(&gpu, &[n], &b).unwrap();
        assert_eq!(ta.read::<f32>().unwrap(), a);
        let mut rec = gpu.recorder().unwrap();
        let c = binary(&mut rec, &ta, &tb, Binary::Add).unwrap();
        rec.submit().unwrap();
        let want: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x + y).collect();
        assert_eq!(c.read::<f32>().unwrap(), want, "n = {n}");
    }
    // Every byte of those uploads and downloads went through staging: two uploads and two
    // downloads of each size.
    let moved: u64 = [0u64, 1, 3, 1000, 100_003].iter().map(|n| 4 * 4 * n).sum();
    assert_eq!(gpu.staged_bytes() - staged, moved, "the transfers did not take the staging path");
    // A view at an offset writes and reads only its own range.
    let al = Tensor::empty(&gpu, &[1], DType::U32).unwrap().view_alignment();
    let len = (3 * al).max(64);
    let base: Vec<u32> = (0..len as u32).collect();
    let t = Tensor::from_slice(&gpu, &[len], &base).unwrap();
    let v = t.view(2 * al, &[5]).unwrap();
    assert_eq!(v.read::<u32>().unwrap(), base[2 * al..2 * al + 5].to_vec());
    v.write(&[7u32; 5]).unwrap();
    let got: Vec<u32> = t.read().unwrap();
    for (i, &g) in got.iter().enumerate() {
        let inside = (2 * al..2 * al + 5).contains(&i);
        assert_eq!(g, if inside { 7 } else { i as u32 }, "element {i}");
    }
}

/// Would catch: an upload that waits for a submission of its own (a host wait per input on a
/// discrete GPU: 22 a small training step, where 3 are the step's), a pending copy that lands
/// after the work that reads it, or one made into a tensor already dropped.
#[test]
fn uploads_ride_with_the_next_submission() {
    let (_one, gpu) = staged_device();
    let mut rng = Rng::new(2);
    let (a, b) = (rng.normal_vec(1000), rng.normal_vec(1000));
    let submits = velox_engine::profile::submits();
    // A recording made before its inputs are written reads what they hold at submission.
    let mut rec = gpu.recorder().unwrap();
    let ta = Tensor::from_slice(&gpu, &[1000], &vec![0.0f32; 1000]).unwrap();
    let tb = Tensor::from_slice(&gpu, &[1000], &b).unwrap();
    let c = binary(&mut rec, &ta, &tb, Binary::Add).unwrap();
    // Written twice before any submission: the second write wins.
    ta.write(&a).unwrap();
    // Uploaded and dropped unread: nothing to copy into.
    drop(Tensor::from_slice(&gpu, &[4096], &rng.normal_vec(4096)).unwrap());
    assert_eq!(velox_engine::profile::submits(), submits, "an upload submitted work of its own");
    rec.submit().unwrap();
    assert_eq!(velox_engine::profile::submits(), submits + 1);
    let want: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x + y).collect();
    assert_eq!(c.read::<f32>().unwrap(), want);
    // A tensor written and read with no recording between: the read's copy takes the upload.
    let t = Tensor::from_slice(&gpu, &[7], &[1u32, 2, 3, 4, 5, 6, 7]).unwrap();
    assert_eq!(t.read::<u32>().unwrap(), vec![1, 2, 3, 4, 5, 6, 7]);
    // A device dropped with an upload no submission took frees it.
    let other = Gpu::new().unwrap();
    let _left = Tensor::from_slice(&other, &[3], &[1.0f32, 2.0, 3.0]).unwrap();
}

/// Would catch: a read back that submits and waits on its own (a training step's losses,
/// gradient norm and tile-pair counts were each a copy and a host wait on a discrete GPU), one
/// that takes a later value of the tensor than where it was asked for, or one readable before
/// its recording ran.
#[test]
fn a_read_back_comes_with_its_recording() {
    let (_one, gpu) = staged_device();
    let mut rng = Rng::new(3);
    let (a, b) = (rng.normal_vec(300), rng.normal_vec(300));
    let ta = Tensor::from_slice(&gpu, &[300], &a).unwrap();
    let tb = Tensor::from_slice(&gpu, &[300], &b).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let c = binary(&mut rec, &ta, &tb, Binary::Add).unwrap();
    let sum = rec.read_back(&c).unwrap();
    // Rewritten later in the same recording: the read back keeps the value it was asked for.
    velox_engine::ops::binary::binary_into(&mut rec, &c, &tb, &c, Binary::Add).unwrap();
    let twice = rec.read_back(&c.view(0, &[7]).unwrap()).unwrap();
    let err = sum.read::<f32>().unwrap_err().to_string();
    assert!(err.contains("before the recording that copies it has run"), "{err}");
    let submits = velox_engine::profile::submits();
    rec.submit().unwrap();
    let want: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x + y).collect();
    assert_eq!(sum.read::<f32>().unwrap(), want);
    let want: Vec<f32> = want.iter().zip(&b).take(7).map(|(x, y)| x + y).collect();
    assert_eq!(twice.read::<f32>().unwrap(), want);
    assert!(sum.read::<u32>().is_err(), "a read back of another type");
    assert_eq!(velox_engine::profile::submits(), submits + 1, "a read back submitted work of its own");
}

/// Would catch: a recording submitted without a wait (`Recorder::launch`) whose results a
/// recording made meanwhile does not see (a missing end barrier, an upload of the second
/// copied ahead of the first's work), a wait that must come in submission order, a read back
/// readable before its recording ran, and a device wait counted while another recording kept
/// the device busy.
#[test]
fn a_recording_made_while_the_last_runs_follows_it() {
    let (_one, gpu) = staged_device();
    let mut rng = Rng::new(4);
    let (a, b, e) = (rng.normal_vec(5000), rng.normal_vec(5000), rng.normal_vec(5000));
    let ta = Tensor::from_slice(&gpu, &[5000], &a).unwrap();
    let tb = Tensor::from_slice(&gpu, &[5000], &b).unwrap();
    let submits = gpu.submits();
    let mut first = gpu.recorder().unwrap();
    let c = binary(&mut first, &ta, &tb, Binary::Add).unwrap();
    let c_read = first.read_back(&c).unwrap();
    let ran = first.completion().clone();
    assert!(!ran.is_submitted());
    let first = first.launch().unwrap();
    assert!(ran.is_submitted() && !ran.is_done());
    // Recorded while the first may run: it reads the first's result, and an upload of its own
    // rides with its submission.
    let mut second = gpu.recorder().unwrap();
    let te = Tensor::from_slice(&gpu, &[5000], &e).unwrap();
    let d = binary(&mut second, &c, &te, Binary::Mul).unwrap();
    let d_read = second.read_back(&d).unwrap();
    let err = c_read.read::<f32>().unwrap_err().to_string();
    assert!(err.contains("before the recording that copies it has run"), "{err}");
    let second = second.launch().unwrap();
    // Waited for out of order.
    let second = second.wait().unwrap();
    assert_eq!(second.host_seconds, 0.0, "the device was busy with the first recording");
    let first = first.wait().unwrap();
    assert!(ran.is_done());
    assert!(first.host_seconds > 0.0);
    let want_c: Vec<f32> = a.iter().zip(&b).map(|(x, y)| x + y).collect();
    let want_d: Vec<f32> = want_c.iter().zip(&e).map(|(x, y)| x * y).collect();
    assert_eq!(c_read.read::<f32>().unwrap(), want_c);
    assert_eq!(d_read.read::<f32>().unwrap(), want_d);
    assert_eq!(gpu.submits(), submits + 2);
    // A recording launched and dropped unwaited waits for the device before it frees its
    // buffers.
    let mut third = gpu.recorder().unwrap();
    let f = binary(&mut third, &d, &d, Binary::Add).unwrap();
    drop(third.launch().unwrap());
    let want_f: Vec<f32> = want_d.iter().map(|x| x + x).collect();
    assert_eq!(f.read::<f32>().unwrap(), want_f);
}

/// Would catch: a staging buffer made and freed for every transfer (the pool unused), or one
/// kept forever (the pool growing with every transfer).
#[test]
fn staging_buffers_are_reused() {
    let (_one, gpu) = staged_device();
    let mut rng = Rng::new(4);
    let t = Tensor::empty(&gpu, &[1000], DType::F32).unwrap();
    for _ in 0..50 {
        let v = rng.normal_vec(1000);
        t.write(&v).unwrap();
        assert_eq!(t.read::<f32>().unwrap(), v);
    }
    // One 4 KiB buffer for the upload and one for the download, taken back each time.
    assert_eq!(gpu.staging_pool_bytes(), 2 * 4096);
}
