//! The recorder's bounds: a submit that waits no longer than it is told, with an error that
//! names the recording.

use crate::common;
use common::*;

use velox_engine::ops::matmul;
use velox_engine::Error;

/// Would catch: a fence wait without a limit (one hung kernel would hold the command forever)
/// and a timeout that does not say which recording it was, or how long it waited.
#[test]
fn a_submit_that_outlasts_its_wait_limit_names_the_recording() {
    let gpu = gpu();
    let n = 256;
    let a = Tensor::from_slice(&gpu, &[n, n], &Rng::new(1).normal_vec(n * n)).unwrap();
    let c = Tensor::empty(&gpu, &[n, n], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    rec.set_label("the wait-limit test");
    // Work no device finishes in the moment between the submit and the first look at its fence.
    for _ in 0..8 {
        matmul::matmul_into(&mut rec, &a, &a, false, false, &c, false).unwrap();
    }
    rec.set_wait_timeout(std::time::Duration::ZERO);
    match rec.submit() {
        Err(Error::Timeout { recording, waited }) => {
            assert!(
                recording.contains("the wait-limit test") && recording.contains("8 dispatches"),
                "{recording}"
            );
            assert!(waited < std::time::Duration::from_secs(60));
            let message = Error::Timeout { recording, waited }.to_string();
            assert!(message.contains("VELOX_WAIT_TIMEOUT"), "{message}");
        }
        other => panic!("expected a timeout, got {:?}", other.map(|f| f.dispatches)),
    }
    // The device is still usable: the recording finished while its recorder was dropped.
    let mut rec = gpu.recorder().unwrap();
    matmul::matmul_into(&mut rec, &a, &a, false, false, &c, false).unwrap();
    rec.submit().unwrap();
    let got: Vec<f32> = c.read().unwrap();
    assert!(got.iter().all(|v| v.is_finite()));
}
