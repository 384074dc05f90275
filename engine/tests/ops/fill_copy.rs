use crate::common;
use common::*;
use velox_engine::ops::fill::fill;
use velox_engine::{Error, Limit};

#[test]
fn fill_every_dtype_and_awkward_sizes() {
    let gpu = gpu();
    for &n in &[0usize, 1, 3, 255, 256, 257, 70_001] {
        let t = Tensor::empty(&gpu, &[n], DType::F32).unwrap();
        let u = Tensor::empty(&gpu, &[n], DType::U32).unwrap();
        let h = Tensor::empty(&gpu, &[n], DType::F16).unwrap();
        let mut rec = gpu.recorder().unwrap();
        fill(&mut rec, &t, -1.25).unwrap();
        fill(&mut rec, &u, 7.0).unwrap();
        fill(&mut rec, &h, 0.5).unwrap();
        rec.submit().unwrap();
        assert!(t.read::<f32>().unwrap().iter().all(|&v| v == -1.25), "f32 n={n}");
        assert!(u.read::<u32>().unwrap().iter().all(|&v| v == 7), "u32 n={n}");
        assert!(h.read::<half::f16>().unwrap().iter().all(|&v| v.to_f32() == 0.5), "f16 n={n}");
    }
}

#[test]
fn copy_then_fill_orders_correctly() {
    // The recorder must put a barrier between the copy that reads `a` and the fill that
    // overwrites it (write after read), and between the fill of `b` and the copy into `b`.
    let gpu = gpu();
    let n = 100_000;
    let data: Vec<f32> = (0..n).map(|i| i as f32).collect();
    let a = Tensor::from_slice(&gpu, &[n], &data).unwrap();
    let b = Tensor::empty(&gpu, &[n], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    fill(&mut rec, &b, 3.0).unwrap();
    rec.copy(&a, &b).unwrap();
    fill(&mut rec, &a, 9.0).unwrap();
    let done = rec.submit().unwrap();
    assert_eq!(done.barriers, 2);
    assert_eq!(b.read::<f32>().unwrap(), data);
    assert!(a.read::<f32>().unwrap().iter().all(|&v| v == 9.0));
}

#[test]
fn tensor_larger_than_one_binding_is_refused() {
    let gpu = gpu();
    let max = gpu.caps().max_storage_buffer_range as usize;
    match Tensor::empty(&gpu, &[max / 4 + 1], DType::F32) {
        Ok(t) => {
            let mut rec = gpu.recorder().unwrap();
            let err = fill(&mut rec, &t, 1.0).unwrap_err();
            assert!(matches!(err, Error::TooLarge { limit: Limit::Binding, .. }), "{err}");
        }
        // Where no buffer can exceed one binding (SwiftShader: 1 GiB each), making it is refused.
        Err(e) => {
            assert!(gpu.caps().max_buffer_size <= max as u64, "{e}");
            assert!(matches!(e, Error::TooLarge { limit: Limit::Buffer, .. }), "{e}");
        }
    }
}

#[test]
fn host_data_of_wrong_size_or_type_is_refused() {
    let gpu = gpu();
    assert!(Tensor::from_slice(&gpu, &[2, 3], &[1.0f32; 5]).is_err());
    let t = Tensor::empty(&gpu, &[4], DType::U32).unwrap();
    assert!(t.write(&[1.0f32; 4]).is_err());
    assert!(t.read::<f32>().is_err());
}

#[test]
fn views_share_storage_and_bind_their_own_range() {
    let gpu = gpu();
    // Room for views at 8 and 16 alignments (4 to 256 bytes, by device), and a tail after them.
    let probe = Tensor::empty(&gpu, &[1], DType::F32).unwrap();
    let n = (16 * probe.view_alignment() + 32).max(1000);
    let data: Vec<f32> = (0..n).map(|i| i as f32).collect();
    let t = Tensor::from_slice(&gpu, &[n], &data).unwrap();
    let a = t.view_alignment();
    let v = t.view(8 * a, &[5, 3]).unwrap();
    assert_eq!(v.read::<f32>().unwrap(), data[8 * a..8 * a + 15].to_vec());
    let w = t.view(16 * a, &[15]).unwrap();
    let mut rec = gpu.recorder().unwrap();
    fill(&mut rec, &v, -1.0).unwrap();
    rec.copy(&v.reshape(&[15]).unwrap(), &w).unwrap();
    rec.submit().unwrap();
    let got: Vec<f32> = t.read().unwrap();
    for (i, &g) in got.iter().enumerate() {
        let inside = (8 * a..8 * a + 15).contains(&i) || (16 * a..16 * a + 15).contains(&i);
        assert_eq!(g, if inside { -1.0 } else { i as f32 }, "element {i}");
    }
    w.write(&[2.0f32; 15]).unwrap();
    assert_eq!(t.read::<f32>().unwrap()[16 * a], 2.0);
    if a > 1 {
        assert!(t.view(1, &[4]).unwrap_err().to_string().contains("multiple"));
    }
    assert!(t.view(n - 4, &[8]).unwrap_err().to_string().contains("past the end"));
}

#[test]
fn row_copies_and_index_concatenation() {
    use velox_engine::ops::concat::{copy_add, reference};
    let gpu = gpu();
    // Rows of 3 f32 at unaligned row offsets, both ways of a 7-row and a 5-row tensor.
    let a: Vec<f32> = (0..21).map(|i| i as f32).collect();
    let ta = Tensor::from_slice(&gpu, &[7, 3], &a).unwrap();
    let tb = Tensor::from_slice(&gpu, &[5, 3], &[-1.0f32; 15]).unwrap();
    let mut rec = gpu.recorder().unwrap();
    rec.copy_rows(&ta, 3, &tb, 1, 3).unwrap();
    rec.submit().unwrap();
    let mut want = vec![-1.0f32; 15];
    want[3..12].copy_from_slice(&a[9..18]);
    assert_eq!(tb.read::<f32>().unwrap(), want);
    let mut rec = gpu.recorder().unwrap();
    assert!(rec.copy_rows(&ta, 5, &tb, 0, 3).is_err(), "past the source's end");
    assert!(rec.copy_rows(&ta, 0, &tb, 3, 3).is_err(), "past the destination's end");
    let other = Tensor::empty(&gpu, &[5, 2], DType::F32).unwrap();
    assert!(rec.copy_rows(&ta, 0, &other, 0, 1).is_err(), "rows of another width");
    rec.copy_rows(&ta, 7, &tb, 5, 0).unwrap();
    drop(rec);

    // Index lists: each piece shifted into the batch's numbering, at awkward sizes.
    for (n, start, count, add) in [(1, 0, 1, 5u32), (300, 17, 257, 1000), (70_001, 1, 70_000, u32::MAX)] {
        let src: Vec<u32> = (0..n as u32).map(|i| i.wrapping_mul(2_654_435_761)).collect();
        let dst0: Vec<u32> = (0..n as u32 + 3).collect();
        let (ts, td) = (
            Tensor::from_slice(&gpu, &[n], &src).unwrap(),
            Tensor::from_slice(&gpu, &[n + 3], &dst0).unwrap(),
        );
        let mut rec = gpu.recorder().unwrap();
        copy_add(&mut rec, &ts, n - count, &td, start + 2, count, add).unwrap();
        rec.submit().unwrap();
        let want = reference::copy_add(&src, n - count, &dst0, start + 2, count, add);
        assert_eq!(td.read::<u32>().unwrap(), want, "n {n}");
    }
    let t = Tensor::from_slice(&gpu, &[4], &[0u32; 4]).unwrap();
    let mut rec = gpu.recorder().unwrap();
    assert!(copy_add(&mut rec, &t, 2, &t, 0, 3, 1).is_err());
    assert!(copy_add(&mut rec, &ta, 0, &t, 0, 1, 1).is_err(), "f32 source");
}

#[test]
fn the_device_counts_the_memory_its_buffers_hold() {
    // Live bytes grow by at least a buffer's size when it is made and shrink when it goes;
    // the peak keeps the most held since it was reset. (Other tests of this binary allocate in
    // parallel, so the checks are bounds, not equalities.)
    let gpu = gpu();
    let bytes = 64 << 20;
    gpu.reset_peak_memory();
    let (before, _) = gpu.memory();
    let t = Tensor::empty(&gpu, &[bytes / 4], DType::F32).unwrap();
    let (live, peak) = gpu.memory();
    assert!(live >= bytes as u64 && peak >= live, "live {live}, peak {peak}");
    drop(t);
    let (after, peak_after) = gpu.memory();
    assert!(peak_after >= bytes as u64, "the peak remembers the buffer: {peak_after}");
    // Where the device is this test's alone while it runs, dropping the tensor gives back
    // exactly what it held (a buffer whose memory is never freed would keep it).
    if !devices_shared(&gpu) {
        assert_eq!(after, before, "live bytes after the tensor went");
    }
}
