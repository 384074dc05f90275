fn main() {
    let gpu = velox_engine::Gpu::new().unwrap_or_else(|e| {
        eprintln!("error: {e}");
        std::process::exit(1)
    });
    println!("{:#?}", gpu.caps());
    let t = velox_engine::Tensor::empty(&gpu, &[1000], velox_engine::DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    rec.timestamp();
    velox_engine::ops::fill::fill(&mut rec, &t, 2.5).unwrap();
    rec.timestamp();
    let f = rec.submit().unwrap();
    let v: Vec<f32> = t.read().unwrap();
    println!("{:?} {:?}", &v[..4], f);
}
