use crate::common;
use common::*;
use velox_engine::ops::scan::{self, exclusive_scan, exclusive_scan_items};
use velox_engine::ops::sort::{self, sort_pairs, Radix};

const SIZES: [usize; 9] = [0, 1, 2, 255, 256, 257, 4095, 4097, 100_003];

/// Scans `data` on the device with `items` elements per invocation and checks every prefix
/// and the total against the reference.
fn check_scan(data: &[u32], items: u32) {
    let gpu = gpu();
    let n = data.len();
    let input = Tensor::from_slice(&gpu, &[n], data).unwrap();
    let output = Tensor::empty(&gpu, &[n], DType::U32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let total = exclusive_scan_items(&mut rec, &input, &output, items).unwrap();
    rec.submit().unwrap();
    let (want, want_total) = scan::reference::exclusive_scan(data);
    let got = output.read::<u32>().unwrap();
    if let Some(i) = (0..n).find(|&i| got[i] != want[i]) {
        panic!("scan n={n} items={items}: first difference at {i}: {} != {}", got[i], want[i]);
    }
    assert_eq!(total.read::<u32>().unwrap(), [want_total], "total n={n}");
}

#[test]
fn scan_matches_reference_on_awkward_sizes() {
    let mut rng = Rng::new(1);
    // With one element per invocation, 65_537 = 256^2 + 1 elements need three levels; with
    // the default 16, 4097 need two.
    for n in SIZES.into_iter().chain([65_536, 65_537]) {
        // Full-range values: the sums wrap around 2^32 many times.
        let data: Vec<u32> = (0..n).map(|_| rng.next_u32()).collect();
        let small: Vec<u32> = (0..n).map(|_| rng.below(4)).collect();
        for items in [1, 3, scan::ITEMS] {
            check_scan(&data, items);
            check_scan(&small, items);
        }
    }
    // The default entry point.
    let data: Vec<u32> = (0..70_001).map(|_| rng.next_u32()).collect();
    let gpu = gpu();
    let input = Tensor::from_slice(&gpu, &[data.len()], &data).unwrap();
    let output = Tensor::empty(&gpu, &[data.len()], DType::U32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let total = exclusive_scan(&mut rec, &input, &output).unwrap();
    rec.submit().unwrap();
    let (want, want_total) = scan::reference::exclusive_scan(&data);
    assert_eq!(output.read::<u32>().unwrap(), want);
    assert_eq!(total.read::<u32>().unwrap(), [want_total]);
}

#[test]
fn scan_with_more_workgroups_than_one_dimension_allows() {
    // 65_537 blocks of 256 (one element per invocation): past the 65_535 workgroups a dispatch
    // dimension is guaranteed to hold (lavapipe allows no more), so the kernels must fold
    // their workgroup index over two dimensions.
    let n = 65_536 * scan::WG + 17;
    let data: Vec<u32> = (0..n as u32).map(|i| i.wrapping_mul(2_654_435_761) >> 24).collect();
    let gpu = gpu();
    let input = Tensor::from_slice(&gpu, &[n], &data).unwrap();
    let output = Tensor::empty(&gpu, &[n], DType::U32).unwrap();
    if !binds_or_refused(&gpu, 4 * n, || exclusive_scan_items(&mut gpu.recorder()?, &input, &output, 1)) {
        return;
    }
    check_scan(&data, 1);
    check_scan(&data, scan::ITEMS);
}

#[test]
fn scan_refuses_bad_arguments() {
    let gpu = gpu();
    let a = Tensor::empty(&gpu, &[10], DType::U32).unwrap();
    let b = Tensor::empty(&gpu, &[11], DType::U32).unwrap();
    let f = Tensor::empty(&gpu, &[10], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    assert!(exclusive_scan(&mut rec, &a, &b).is_err());
    assert!(exclusive_scan(&mut rec, &a, &f).is_err());
    assert!(exclusive_scan(&mut rec, &a, &a).is_err());
    let c = Tensor::empty(&gpu, &[10], DType::U32).unwrap();
    for items in [0, scan::MAX_ITEMS + 1] {
        assert!(exclusive_scan_items(&mut rec, &a, &c, items).is_err());
    }
    // Shapes may differ when the element counts agree.
    let d = Tensor::empty(&gpu, &[2, 5], DType::U32).unwrap();
    assert!(exclusive_scan(&mut rec, &a, &d).is_ok());
}

/// Sorts on the device and checks keys and values exactly against the stable reference.
fn check_sort(keys: &[u32], key_bits: u32, what: &str) {
    let gpu = gpu();
    let n = keys.len();
    // Values are the original indices, so equal keys out of order show up as a difference.
    let values: Vec<u32> = (0..n as u32).collect();
    let k = Tensor::from_slice(&gpu, &[n], keys).unwrap();
    let v = Tensor::from_slice(&gpu, &[n], &values).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let (sk, sv) = sort_pairs(&mut rec, &k, &v, key_bits).unwrap();
    rec.submit().unwrap();
    let (want_k, want_v) = sort::reference::sort_pairs(keys, &values, key_bits);
    let (got_k, got_v) = (sk.read::<u32>().unwrap(), sv.read::<u32>().unwrap());
    if let Some(i) = (0..n).find(|&i| got_k[i] != want_k[i] || got_v[i] != want_v[i]) {
        panic!(
            "{what} n={n} key_bits={key_bits}: first difference at {i}: ({}, {}) != ({}, {})",
            got_k[i], got_v[i], want_k[i], want_v[i]
        );
    }
    // The inputs are left as they were.
    assert_eq!(k.read::<u32>().unwrap(), keys, "{what}: keys changed");
    assert_eq!(v.read::<u32>().unwrap(), values, "{what}: values changed");
}

#[test]
fn sort_random_keys_with_many_duplicates_is_stable() {
    let mut rng = Rng::new(2);
    for n in SIZES {
        let keys: Vec<u32> = (0..n).map(|_| rng.below(300)).collect();
        check_sort(&keys, 32, "duplicates");
        let keys: Vec<u32> = (0..n).map(|_| rng.next_u32()).collect();
        check_sort(&keys, 32, "full range");
    }
}

#[test]
fn sort_on_few_key_bits_orders_by_the_low_bits_only() {
    // Every key has high bits set above `key_bits`: they must neither order the keys nor be
    // lost from them.
    // One block (every pass in one dispatch, odd and even numbers of passes) and several.
    let mut rng = Rng::new(3);
    for key_bits in [1, 4, 9, 13, 32] {
        for n in [300, 4096, 4097, 100_003] {
            let keys: Vec<u32> = (0..n).map(|_| rng.next_u32() | 0x8000_0000).collect();
            check_sort(&keys, key_bits, "high bits set");
        }
    }
    // Tile-and-depth style keys: few distinct low parts, many high parts.
    let keys: Vec<u32> = (0..20_000).map(|_| (rng.next_u32() << 7) | rng.below(100)).collect();
    check_sort(&keys, 7, "packed");
}

#[test]
fn sort_equal_sorted_and_reversed_input() {
    let n = 10_007u32;
    check_sort(&vec![42; n as usize], 32, "all equal");
    check_sort(&vec![u32::MAX; n as usize], 32, "all max");
    let sorted: Vec<u32> = (0..n).map(|i| i / 3).collect();
    check_sort(&sorted, 32, "sorted");
    let reversed: Vec<u32> = (0..n).rev().map(|i| i * 65_537).collect();
    check_sort(&reversed, 32, "reversed");
    check_sort(&reversed, 16, "reversed, 16 bits");
}

#[test]
fn sort_moves_f32_values_and_keeps_shapes() {
    let gpu = gpu();
    let keys: Vec<u32> = vec![3, 1, 2, 1, 0, 3];
    let values: Vec<f32> = vec![0.5, -1.0, 2.25, f32::INFINITY, 7.0, -0.0];
    let k = Tensor::from_slice(&gpu, &[2, 3], &keys).unwrap();
    let v = Tensor::from_slice(&gpu, &[2, 3], &values).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let (sk, sv) = sort_pairs(&mut rec, &k, &v, 2).unwrap();
    rec.submit().unwrap();
    assert_eq!(sk.shape(), [2, 3]);
    assert_eq!(sv.dtype(), DType::F32);
    assert_eq!(sk.read::<u32>().unwrap(), [0, 1, 1, 2, 3, 3]);
    let got: Vec<u32> = sv.read::<f32>().unwrap().iter().map(|x| x.to_bits()).collect();
    let want: Vec<u32> = [7.0f32, -1.0, f32::INFINITY, 2.25, 0.5, -0.0].iter().map(|x| x.to_bits()).collect();
    assert_eq!(got, want);
}

#[test]
fn every_way_of_sorting_sorts_alike() {
    // 4-bit digits counted by atomics and by subgroup adds, and 8-bit digits ranked by subgroup
    // ballots, on one device: every sort is the reference's (keys and the values that say the
    // order is stable), over several blocks with a partial last one, on full and on narrow keys
    // (13 bits: a last 8-bit pass of 5), on keys of few values (groups of equal digits as wide
    // as a subgroup, and runs of one digit across rounds and subgroups), with values given and
    // with the indices the kernels make. Where the device cannot sort a way, asking for it is
    // an error that says what it lacks.
    let gpu = gpu();
    let c = gpu.caps();
    let bytes_possible =
        c.subgroup_ballot && c.subgroup_shuffle && c.min_subgroup_size >= 8 && c.max_subgroup_size <= 128;
    // The rule: a CPU device keeps 4-bit digits and atomics; a GPU that can rank bytes takes them.
    let want_chosen = if c.cpu_kernels {
        Radix::Atomics
    } else if bytes_possible {
        Radix::Bytes
    } else if c.subgroup_arithmetic {
        Radix::Subgroups
    } else {
        Radix::Atomics
    };
    assert_eq!(Radix::chosen(&gpu), want_chosen);
    let mut rng = Rng::new(12);
    let cases: [(usize, u32, u32); 5] = [
        (3 * sort::BLOCK + 77, 32, 0),
        (5 * sort::BLOCK, 13, 0),
        (sort::BLOCK + 1, 4, 0),
        (2 * sort::BLOCK + 999, 16, 3),
        (3 * sort::BLOCK, 24, 1),
    ];
    for (n, bits, few) in cases {
        // `few` > 0: keys of 2^few values spread over the key's bits.
        let keys: Vec<u32> = (0..n)
            .map(|_| match few {
                0 => rng.below(1 << (bits - 1)) * 2 + rng.below(2),
                _ => rng.below(1 << few).wrapping_mul(0x9e37_79b1) >> (32 - bits),
            })
            .collect();
        let values: Vec<u32> = (0..n as u32).collect();
        let want = sort::reference::sort_pairs(&keys, &values, bits);
        let k = Tensor::from_slice(&gpu, &[n], &keys).unwrap();
        let v = Tensor::from_slice(&gpu, &[n], &values).unwrap();
        for radix in Radix::ALL {
            for indices in [false, true] {
                let mut rec = gpu.recorder().unwrap();
                let sorted = match indices {
                    false => sort::sort_pairs_with(&mut rec, &k, &v, bits, radix),
                    true => sort::sort_indices_with(&mut rec, &k, bits, radix),
                };
                let (sk, sv) = match sorted {
                    Ok(out) => out,
                    Err(e) if radix == Radix::Subgroups && !c.subgroup_arithmetic => {
                        assert!(e.to_string().contains("histogram_subgroups"), "{e}");
                        continue;
                    }
                    Err(e) if radix == Radix::Bytes && !bytes_possible => {
                        assert!(e.to_string().contains("subgroup"), "{e}");
                        continue;
                    }
                    Err(e) => panic!("{radix:?}: {e}"),
                };
                rec.submit().unwrap();
                let got = (sk.read::<u32>().unwrap(), sv.read::<u32>().unwrap());
                assert!(
                    got == want,
                    "{radix:?}, {n} keys of {bits} bits ({} values{}): not the reference's order",
                    if few > 0 { 1 << few } else { n },
                    if indices { ", indices made by the kernels" } else { "" }
                );
            }
        }
    }
}

#[test]
fn sort_refuses_bad_arguments() {
    let gpu = gpu();
    let k = Tensor::empty(&gpu, &[10], DType::U32).unwrap();
    let v = Tensor::empty(&gpu, &[10], DType::U32).unwrap();
    let short = Tensor::empty(&gpu, &[9], DType::U32).unwrap();
    let fk = Tensor::empty(&gpu, &[10], DType::F32).unwrap();
    let h = Tensor::empty(&gpu, &[10], DType::F16).unwrap();
    let mut rec = gpu.recorder().unwrap();
    for bits in [0, 33] {
        let err = sort_pairs(&mut rec, &k, &v, bits).unwrap_err().to_string();
        assert!(err.contains("key_bits"), "{err}");
    }
    assert!(sort_pairs(&mut rec, &k, &short, 32).is_err());
    assert!(sort_pairs(&mut rec, &fk, &v, 32).is_err());
    assert!(sort_pairs(&mut rec, &k, &h, 32).is_err());
}
