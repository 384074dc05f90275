mod common;
use common::*;
use velox::engine::ops::fill::fill;

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
        assert!(
            t.read::<f32>().unwrap().iter().all(|&v| v == -1.25),
            "f32 n={n}"
        );
        assert!(
            u.read::<u32>().unwrap().iter().all(|&v| v == 7),
            "u32 n={n}"
        );
        assert!(
            h.read::<half::f16>()
                .unwrap()
                .iter()
                .all(|&v| v.to_f32() == 0.5),
            "f16 n={n}"
        );
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
    let t = Tensor::empty(&gpu, &[max / 4 + 1], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let err = fill(&mut rec, &t, 1.0).unwrap_err().to_string();
    assert!(err.contains("too large"), "{err}");
}

#[test]
fn host_data_of_wrong_size_or_type_is_refused() {
    let gpu = gpu();
    assert!(Tensor::from_slice(&gpu, &[2, 3], &[1.0f32; 5]).is_err());
    let t = Tensor::empty(&gpu, &[4], DType::U32).unwrap();
    assert!(t.write(&[1.0f32; 4]).is_err());
    assert!(t.read::<f32>().is_err());
}
