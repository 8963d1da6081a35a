//! Observation files: round trips, hostile headers and sidecars, and the errors they give.

use super::*;

#[test]
fn round_trip_and_atomic_names() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("obs.npy");
    let geo = Geometry::new(16.0, 4, 8, 1).unwrap();
    let mut counts = CountMatrix::zeros(8, 8);
    counts.counts[3] = 5;
    let obs = fractions(&counts, 10);
    let mut side = Sidecar::for_render(&geo, 10);
    side.seed = Some(3);
    write(&path, &obs, &side).unwrap();
    let (back, back_side) = read(&path).unwrap();
    assert_eq!(back[[0, 3]], 0.5);
    assert_eq!(back_side, side);
    // Only the two files remain: no temporary left behind.
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
}

#[test]
fn mismatched_shape_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("obs.npy");
    let geo = Geometry::new(16.0, 4, 8, 1).unwrap();
    write(&path, &Array2::zeros((4, 4)), &Sidecar::for_render(&geo, 1)).unwrap();
    let e = read(&path).unwrap_err().to_string();
    assert!(
        e.contains("does not match its geometry") && e.contains("obs.npy"),
        "{e}"
    );
}

/// An NPY file's bytes: a version 1.0 header of `dict`, then `data`.
fn npy(dict: &str, data: &[u8]) -> Vec<u8> {
    let mut header = dict.to_string();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

fn sidecar(positions: u32, directions: u32) -> Vec<u8> {
    let geo = Geometry::new(16.0, 1, positions, directions).unwrap();
    serde_json::to_vec(&Sidecar::for_render(&geo, 100)).unwrap()
}

fn floats(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

const GOOD: &str = "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4), }";

fn refusal(npy_bytes: &[u8], side: &[u8]) -> String {
    match read_bytes(npy_bytes, side, Path::new("evil.npy")) {
        Ok(_) => panic!("accepted"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn a_huge_claimed_shape_is_refused_before_allocating() {
    // The file: 100 bytes claiming (2³⁰, 2³⁰) float32.
    let evil = npy(
        "{'descr': '<f4', 'fortran_order': False, 'shape': (1073741824, 1073741824), }",
        &[],
    );
    let e = refusal(&evil, &sidecar(4, 1));
    assert!(
        e.contains("evil.npy")
            && e.contains("[1073741824, 1073741824]")
            && e.contains("needs [4, 4]"),
        "{e}"
    );
    // Matching the sidecar is not enough: the data cap holds too.
    let big = npy(
        "{'descr': '<f4', 'fortran_order': False, 'shape': (65536, 65536), }",
        &[],
    );
    let e = refusal(&big, &sidecar(65536, 1));
    assert!(e.contains("more than the 1073741824 bytes"), "{e}");
    // And so does the length: header plus data exactly.
    let e = refusal(&npy(GOOD, &floats(&[0.0; 15])), &sidecar(4, 1));
    assert!(e.contains("is 188 bytes, expected 192"), "{e}");
    let e = refusal(&npy(GOOD, &floats(&[0.0; 17])), &sidecar(4, 1));
    assert!(e.contains("expected 192"), "{e}");
}

#[test]
fn header_fields_are_checked() {
    let side = sidecar(4, 1);
    let data = floats(&[0.0; 16]);
    for (dict, expect) in [
        (
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4, 4), }",
            "'<f4'",
        ),
        (
            "{'descr': '>f4', 'fortran_order': False, 'shape': (4, 4), }",
            "'<f4'",
        ),
        (
            "{'descr': '<f4', 'fortran_order': True, 'shape': (4, 4), }",
            "C (row-major)",
        ),
        (
            "{'descr': '<f4', 'fortran_order': False, 'shape': (16,), }",
            "expected 2-D",
        ),
        (
            "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4, 1), }",
            "expected 2-D",
        ),
        ("{'descr': '<f4', 'fortran_order': False, }", "no shape"),
        ("{'descr': '<f4', 'shape': (4, 4), }", "fortran_order"),
        (
            "{'descr': '<f4', 'descr': '<f4', 'fortran_order': False, 'shape': (4, 4)}",
            "twice",
        ),
        (
            "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4), 'x': 1}",
            "unknown header key",
        ),
        (
            "{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999999999999999, 4)}",
            "too large",
        ),
        (
            "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 4)",
            "expected '}'",
        ),
    ] {
        let e = refusal(&npy(dict, &data), &side);
        assert!(e.contains("evil.npy") && e.contains(expect), "{dict}: {e}");
    }
    let mut bad = npy(GOOD, &data);
    bad[0] = b'X';
    assert!(refusal(&bad, &side).contains("magic"));
    let mut bad = npy(GOOD, &data);
    bad[6] = 4;
    assert!(refusal(&bad, &side).contains("version 4.0"));
    // A huge header length (version 2: 32 bits) is refused before it is read.
    let mut bad = b"\x93NUMPY\x02\x00".to_vec();
    bad.extend_from_slice(&u32::MAX.to_le_bytes());
    let e = refusal(&bad, &side);
    assert!(
        e.contains("4294967295 bytes, expected at most 16384"),
        "{e}"
    );
    // A header longer than the file.
    let good = npy(GOOD, &data);
    assert!(refusal(&good[..40], &side).contains("the file ends after"));
    assert!(refusal(&good[..9], &side).contains("magic"));
    // Version 2 and 3 headers and a Python-2 long are read.
    let mut v2 = b"\x93NUMPY\x03\x00".to_vec();
    let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (4L, 4L), }\n";
    v2.extend_from_slice(&(dict.len() as u32).to_le_bytes());
    v2.extend_from_slice(dict.as_bytes());
    v2.extend_from_slice(&data);
    assert!(read_bytes(&v2, &side, Path::new("v3.npy")).is_ok());
}

#[test]
fn bad_values_are_refused_with_their_index() {
    let side = sidecar(4, 1);
    for (bad, shown) in [(f32::NAN, "NaN"), (f32::INFINITY, "inf"), (-0.5, "-0.5")] {
        let mut values = [0.25; 16];
        values[2 * 4 + 3] = bad;
        let e = refusal(&npy(GOOD, &floats(&values)), &side);
        assert!(
            e.contains("evil.npy") && e.contains("row 2, column 3") && e.contains(shown),
            "{e}"
        );
    }
    let (data, _) =
        read_bytes(&npy(GOOD, &floats(&[0.25; 16])), &side, Path::new("ok.npy")).unwrap();
    assert_eq!(data[[3, 3]], 0.25);
}

#[test]
fn sidecar_errors_name_the_file_and_key() {
    let data = npy(GOOD, &floats(&[0.0; 16]));
    let good: serde_json::Value = serde_json::from_slice(&sidecar(4, 1)).unwrap();
    let with = |key: &str, v: serde_json::Value| {
        let mut s = good.clone();
        match v {
            serde_json::Value::Null => {
                s.as_object_mut().unwrap().remove(key);
            }
            v => {
                s[key] = v;
            }
        }
        serde_json::to_vec(&s).unwrap()
    };
    use serde_json::json;
    for (key, v, expect) in [
        ("positions", json!("4"), "got \"4\""),
        ("positions", json!(6), "divisible by 4"),
        ("positions", json!(-4), "got -4"),
        ("positions", serde_json::Value::Null, "missing"),
        ("directions", json!(0), ">= 1"),
        ("directions", json!(100000), "65536"),
        ("size_mm", json!(0), "> 0"),
        ("photons_per_source", json!(0), ">= 1"),
        ("format", json!("other"), "scatterfarm-observation/1"),
        ("seed", json!(1.5), "whole number"),
        ("engine", json!([1]), "got an array"),
    ] {
        let e = refusal(&data, &with(key, v));
        assert!(
            e.contains("evil.json") && e.contains(&format!("`{key}`")) && e.contains(expect),
            "{key}: {e}"
        );
    }
    let e = refusal(&data, b"{\"format\": ");
    assert!(e.contains("evil.json") && e.contains("EOF"), "{e}");
    let e = refusal(&data, b"[1, 2]");
    assert!(e.contains("evil.json") && e.contains("an array"), "{e}");
}

#[test]
fn oversized_files_are_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.json");
    let f = std::fs::File::create(&path).unwrap();
    f.set_len(MAX_SIDECAR_BYTES + 1).unwrap();
    let e = read_capped(&path, MAX_SIDECAR_BYTES, "observation sidecar")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("big.json") && e.contains("more than the 1048576 bytes"),
        "{e}"
    );
}
