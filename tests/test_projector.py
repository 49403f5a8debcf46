"""Stage B: sLSBH by hand, tie rule, projection determinism, the .bin format."""

import numpy as np
import pytest

from neoslam_stream.algorithms import projection as PM
from neoslam_stream.algorithms import projector as P
from neoslam_stream.algorithms import weights as W
from neoslam_stream.algorithms.errors import InvalidInput
from neoslam_stream.nodes.frontend import make_node
from neoslam_stream.runtime.messages import Message


def b_node(**projector):
    """Stage B's node with these projector parameters."""
    return make_node("codes", projector=projector)


def test_slsbh_hand_made_vector():
    # 8 dims, s = 25 %: k = 2 largest -> bits j, 2 smallest -> bits 8 + j
    d = np.array([0.5, -3.0, 9.0, 1.0, -1.0, 7.0, 0.0, -2.0], dtype=np.float32)
    bits = P.slsbh(d, 0.25)
    assert bits.tolist() == [2, 5, 8 + 1, 8 + 7]


def test_slsbh_tie_rule_lower_index_wins():
    d = np.array([1.0, 5.0, 5.0, 5.0, -4.0, -4.0, -4.0, 0.0], dtype=np.float32)
    bits = P.slsbh(d, 0.25)
    # largest: three 5.0 tie for two places -> indices 1 and 2; smallest: -4.0 x3 -> 4 and 5
    assert bits.tolist() == [1, 2, 8 + 4, 8 + 5]


def test_slsbh_exactly_512_of_2048_top_and_bottom_quartiles():
    rng = np.random.default_rng(0)
    d = rng.standard_normal(1024).astype(np.float32)
    bits = P.slsbh(d)
    assert bits.size == 512 and bits.dtype == np.uint16 and np.all(np.diff(bits.astype(int)) > 0)
    top = bits[bits < 1024]
    bottom = bits[bits >= 1024] - 1024
    assert top.size == 256 and bottom.size == 256
    # the paper's definition: the top quartile's smallest value exceeds every unmarked value
    rest = np.setdiff1d(np.arange(1024), top)
    assert d[top].min() > d[rest].max()
    rest = np.setdiff1d(np.arange(1024), bottom)
    assert d[bottom].max() < d[rest].min()
    # and not the ROS 2 C++ behaviour (smallest quartile in the first half)
    assert set(top).isdisjoint(set(np.argsort(d)[:256]))


def test_gaussian_matrix_is_seeded_standard_normal_float32():
    a = PM.gaussian_matrix(300, seed=5, m=64)
    b = PM.gaussian_matrix(300, seed=5, m=64)
    c = PM.gaussian_matrix(300, seed=6, m=64)
    assert a.dtype == np.float32 and a.shape == (300, 64)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert abs(a.mean()) < 0.02 and abs(a.std() - 1) < 0.02


def test_projection_is_p_times_f():
    bp = P.BinaryProjector(input_dim=50, seed=3)
    f = np.random.default_rng(1).standard_normal(50).astype(np.float32)
    expected = np.array([np.dot(bp.matrix[:, j], f) for j in range(1024)], dtype=np.float64)
    np.testing.assert_allclose(bp.project(f), expected, rtol=1e-4, atol=1e-4)


def test_bin_round_trip_and_size_check(tmp_path):
    m = PM.gaussian_matrix(40, seed=1)
    path = tmp_path / "randomMatrix.bin"
    W.save_bin(m, path)
    assert path.stat().st_size == 40 * 1024 * 4  # no header
    loaded = W.load_bin(path, 40)
    np.testing.assert_array_equal(loaded, m)
    raw = np.fromfile(path, dtype="<f4")
    assert raw[1025] == m[1, 1]  # row-major (n, 1024)
    with pytest.raises(ValueError, match="bytes"):
        W.load_bin(path, 41)
    bp = P.BinaryProjector(input_dim=40, matrix_path=str(path))
    np.testing.assert_array_equal(bp.matrix, m)


def test_full_size_bin_has_the_ros2_byte_count():
    assert 64896 * 1024 * 4 == 265_814_016


def test_sparse_projection_density_and_values():
    sp = PM.sparse_matrix(10000, seed=0)
    density = sp.nnz / (10000 * 1024)
    assert density == pytest.approx(1 / np.sqrt(10000), rel=0.05)
    vals = np.unique(np.abs(sp.data))
    np.testing.assert_allclose(vals, [np.sqrt(np.sqrt(10000))], rtol=1e-6)


def test_stage_batches_and_validates_length():
    st = b_node(input_dim=100, seed=2)
    st.setup()
    rng = np.random.default_rng(0)
    msgs = [Message("visual_features", i, 0.0, {"features": rng.standard_normal(100).astype(np.float32)})
            for i in range(3)]
    out = st.process_batch("visual_features", msgs)
    assert len(out) == 3 and all(m["bits"].size == 512 for _, m in out)
    np.testing.assert_array_equal(out[1][1]["bits"], st.core.projector.bits(msgs[1]["features"]))
    with pytest.raises(InvalidInput):
        st.process("visual_features", Message("visual_features", 9, 0.0, {"features": np.zeros(7, np.float32)}))


def test_projection_does_not_depend_on_batching():
    # micro-batching must not change results: lossless runs are repeatable whatever the batch sizes
    bp = P.BinaryProjector(input_dim=3000, seed=4)
    F = np.random.default_rng(5).standard_normal((8, 3000)).astype(np.float32)
    whole = bp.project(F)
    for size in (1, 2, 3, 5):
        parts = np.concatenate([bp.project(F[i:i + size]) for i in range(0, 8, size)])
        np.testing.assert_array_equal(parts, whole)
    np.testing.assert_array_equal(bp.project(F[3]), whole[3])


def test_compiled_slsbh_of_a_batch_follows_the_definition():
    # bits_batch uses a compiled sLSBH; check it against the definition on a vector with ties
    bp = P.BinaryProjector(input_dim=20, seed=2)
    f = np.random.default_rng(3).standard_normal((4, 20)).astype(np.float32)
    d = bp.project(f)
    for row, bits in zip(d, bp.bits_batch(f), strict=True):
        top = set(np.argsort(-row, kind="stable")[:256].tolist())
        bottom = {1024 + j for j in np.argsort(row, kind="stable")[:256].tolist()}
        assert bits.tolist() == sorted(top | bottom)


def test_centring_subtracts_the_running_mean_frame_by_frame():
    # W = 2: m_1 = f_1, m_2 = (f_1 + f_2) / 2, m_3 = m_2 + (f_3 - m_2) / 2 (window reached)
    f = np.array([[2.0, 4.0], [4.0, 0.0], [10.0, 10.0]], dtype=np.float32)
    bp = P.BinaryProjector(input_dim=2, seed=0, centre_window=2)
    out = bp.centre(f)
    np.testing.assert_allclose(out, [[0, 0], [1, -2], [3.5, 4.0]])
    # one frame at a time gives the same, so micro-batching cannot change the bits
    bq = P.BinaryProjector(input_dim=2, seed=0, centre_window=2)
    np.testing.assert_allclose(np.stack([bq.centre(r) for r in f]), out)


def test_centring_off_by_default_and_state_round_trip():
    rng = np.random.default_rng(4)
    f = rng.standard_normal((6, 30)).astype(np.float32)
    plain = P.BinaryProjector(input_dim=30, seed=1)
    assert plain.config.centre_window == 0
    np.testing.assert_array_equal(plain.centre(f), f)
    a = P.BinaryProjector(input_dim=30, seed=1, centre_window=4)
    a.bits_batch(f[:3])
    b = P.BinaryProjector(input_dim=30, seed=1, centre_window=4)
    b.load_state_dict(a.state_dict())
    for x, y in zip(a.bits_batch(f[3:]), b.bits_batch(f[3:]), strict=True):
        np.testing.assert_array_equal(x, y)
    # a common offset on every frame is removed by centring: bits equal those without it
    c = P.BinaryProjector(input_dim=30, seed=1, centre_window=4)
    d = P.BinaryProjector(input_dim=30, seed=1, centre_window=4)
    for x, y in zip(c.bits_batch(f), d.bits_batch(f + 100.0), strict=True):
        assert len(set(x.tolist()) ^ set(y.tolist())) <= 4  # float rounding may flip a marginal bit


def test_a_running_mean_made_with_another_window_or_size_is_refused():
    a = P.BinaryProjector(input_dim=30, seed=1, centre_window=4)
    a.bits_batch(np.ones((2, 30), np.float32))
    with pytest.raises(ValueError, match=r"centre_window: the state was made with 4, the config has 8"):
        P.BinaryProjector(input_dim=30, seed=1, centre_window=8).load_state_dict(a.state_dict())
    with pytest.raises(ValueError, match=r"input_dim"):
        P.BinaryProjector(input_dim=31, seed=1, centre_window=4).load_state_dict(a.state_dict())


def test_nan_features_are_rejected():
    bp = P.BinaryProjector(input_dim=10, seed=0, centre_window=3)
    bad = np.zeros(10, np.float32)
    bad[2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        bp.bits(bad)
    assert bp.n_seen == 0  # a rejected frame leaves the running mean alone
    with pytest.raises(ValueError, match="one feature vector"):  # several rows: bits_batch
        bp.bits(np.zeros((2, 10), np.float32))
    with pytest.raises(ValueError, match="features of shape"):  # the wrong length
        bp.bits(np.zeros(9, np.float32))
    stage = b_node(input_dim=10)
    stage.setup()
    msg = Message("visual_features", 3, 0.3, {"features": bad, "backbone": "random_alexnet"})
    with pytest.raises(InvalidInput, match="NaN"):
        stage.process("visual_features", msg)


# ------------------------------------------------------------------ float16 storage of P

def test_half_widening_is_exact_for_every_finite_half():
    # P stored as binary16 bit patterns: the kernel must read each as exactly the float32 value
    # IEEE 754 gives it (numpy's float16 -> float32 is the reference). One row of W holding all
    # 63 488 finite patterns, f = [1]: out = 0 + 1 * w + 0, exact (-0 reads as +0).
    allh = np.arange(65536, dtype=np.uint16)
    finite = allh[np.isfinite(allh.view(np.float16))]
    out = np.empty((1, finite.size), np.float32)
    PM.project_rows(np.ones((1, 1), np.float32), finite.reshape(1, -1), out)
    np.testing.assert_array_equal(out[0], finite.view(np.float16).astype(np.float32))


def test_float16_storage_equals_float32_on_the_rounded_matrix():
    # the float16 path computes exactly what the float32 path computes on P rounded to half
    # (same summation order, float32 accumulators): equal bits, not merely close values
    f16 = P.BinaryProjector(input_dim=3001, seed=4, matrix_dtype="float16")
    ref = P.BinaryProjector(input_dim=3001, seed=4)
    assert f16.matrix.dtype == np.uint16 and f16.matrix.nbytes == ref.matrix.nbytes // 2
    rounded = ref.matrix.astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(f16.matrix_float32(), rounded)  # the same draws, rounded
    ref.matrix = rounded
    F = np.random.default_rng(6).standard_normal((5, 3001)).astype(np.float32)
    np.testing.assert_array_equal(f16.project(F).view(np.uint32), ref.project(F).view(np.uint32))
    for a, b in zip(f16.bits_batch(F), ref.bits_batch(F), strict=True):
        np.testing.assert_array_equal(a, b)
    # and it is still d = P f (with P's rounded entries)
    expected = F.astype(np.float64) @ rounded.astype(np.float64)
    np.testing.assert_allclose(f16.project(F), expected, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("dtype,feature_bits", [("float32", 16), ("float16", 16), ("int8", 16), ("int8", 7)])
def test_projection_does_not_depend_on_batching_or_threads(dtype, feature_bits):
    bp = P.BinaryProjector(input_dim=3001, seed=4, matrix_dtype=dtype, feature_bits=feature_bits)
    F = np.random.default_rng(5).standard_normal((8, 3001)).astype(np.float32)
    whole = bp._project(F)
    for size in (1, 3, 5):
        parts = np.concatenate([bp._project(F[i:i + size]) for i in range(0, 8, size)])
        np.testing.assert_array_equal(parts, whole)
    two = P.BinaryProjector(input_dim=3001, seed=4, matrix_dtype=dtype, feature_bits=feature_bits, threads=2)
    np.testing.assert_array_equal(two._project(F), whole)


def test_bin_round_trip_with_float16_storage(tmp_path):
    # the .bin file stays float32: import rounds it to half in memory, export writes float32
    m = PM.gaussian_matrix(40, seed=1)
    path = tmp_path / "randomMatrix.bin"
    W.save_bin(m, path)
    bp = P.BinaryProjector(input_dim=40, matrix_path=str(path), matrix_dtype="float16")
    np.testing.assert_array_equal(bp.matrix_float32(), m.astype(np.float16).astype(np.float32))
    out = tmp_path / "exported.bin"
    W.save_bin(bp.matrix_float32(), out)
    assert out.stat().st_size == 40 * 1024 * 4
    np.testing.assert_array_equal(W.load_bin(out, 40), m.astype(np.float16).astype(np.float32))
    full = P.BinaryProjector(input_dim=40, matrix_path=str(path))
    np.testing.assert_array_equal(full.matrix_float32(), m)
    with pytest.raises(ValueError, match="literal_error|float32"):
        P.BinaryProjector(input_dim=40, matrix_dtype="int4")


# ------------------------------------------------------------------ int8 storage of P

def test_int8_storage_rounds_the_same_draws_to_a_grid_of_max_over_127():
    ref = P.BinaryProjector(input_dim=3001, seed=4)
    i8 = P.BinaryProjector(input_dim=3001, seed=4, matrix_dtype="int8")
    assert i8.matrix.dtype == np.int8 and i8.matrix.nbytes == ref.matrix.nbytes // 4
    peak = float(np.abs(ref.matrix).max())
    assert i8.matrix_scale == pytest.approx(peak / 127, rel=1e-12)
    assert np.abs(i8.matrix).max() == 127  # the largest |entry| maps to the grid's end
    # every entry is the nearest grid point of its float32 draw: error at most half a step
    err = np.abs(i8.matrix.astype(np.float64) * i8.matrix_scale - ref.matrix.astype(np.float64))
    assert err.max() <= i8.matrix_scale / 2 * (1 + 1e-9)
    np.testing.assert_allclose(i8.matrix_float32(), i8.matrix.astype(np.float64) * i8.matrix_scale, rtol=1e-7)


def test_int8_projection_is_the_exact_integer_product_of_the_rounded_features():
    # the definition: x = rint(f / s_f), s_f = max|f| / 32767; d = s_f s_P (x q), summed exactly.
    # numpy's int64 matrix product is the reference (exact integers); a zero frame gives d = 0
    i8 = P.BinaryProjector(input_dim=1001, seed=3, matrix_dtype="int8")
    F = np.random.default_rng(1).standard_normal((4, 1001)).astype(np.float32) * 50
    F[2] = 0.0
    F[3, 7] = 1e6  # one huge feature: the others round to few levels, still exact
    x = np.empty((4, 1001), np.int64)
    s_f = np.abs(F.astype(np.float64)).max(axis=1) / 32767
    for r in range(4):
        x[r] = np.rint(F[r] / s_f[r]) if s_f[r] > 0 else 0
    assert np.abs(x).max() == 32767
    sums = x @ i8.matrix.astype(np.int64)
    expected = sums * (s_f * i8.matrix_scale)[:, None]
    np.testing.assert_array_equal(i8._project(F), expected)
    np.testing.assert_array_equal(i8.project(F), expected.astype(np.float32))
    for r, bits in enumerate(i8.bits_batch(F)):
        np.testing.assert_array_equal(bits, P.slsbh(expected[r]))


def test_int8_kernel_accumulates_extreme_values_without_overflow():
    # |x| = 32767, |q| = 127 on every row: 3000 rows sum to 1.25e10 (past int32), exactly
    n = 3000
    X = np.full((2, n), 32767, np.int32)
    X[1] = -32767
    Q = np.full((n, 1024), 127, np.int8)
    Q[:, 1] = -127
    out = np.empty((2, 1024), np.int64)
    PM.project_rows_int8(X, Q, out)
    assert out[0, 0] == n * 32767 * 127 and out[0, 1] == -n * 32767 * 127
    assert out[1, 0] == -n * 32767 * 127


def test_seven_bit_features_on_their_grid_give_the_exact_integer_product():
    # features that already lie on a 7-bit grid: f = s (k - z) with k in 0..127, both ends present,
    # so the per-frame quantiser must recover s = (max - min) / 127 and zero point z exactly, and
    # d = s s_P ((k - z) q) is known in integers (n = 1000: |sums| < 2^24, float32 holds them)
    n = 1000
    fast = P.BinaryProjector(input_dim=n, seed=3, matrix_dtype="int8", feature_bits=7)
    exact = P.BinaryProjector(input_dim=n, seed=3, matrix_dtype="int8")
    np.testing.assert_array_equal(fast.matrix, exact.matrix)
    rng = np.random.default_rng(2)
    for s, z in ((0.5, 40), (0.25, 0), (2.0, 127)):
        k = rng.integers(0, 128, n)
        k[:2] = (0, 127)
        f = (s * (k - z)).astype(np.float32)
        sums = (k - z).astype(np.int64) @ fast.matrix.astype(np.int64)
        expected = sums * (s * fast.matrix_scale)
        np.testing.assert_allclose(fast.project(f), expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())


def test_seven_bit_features_stay_close_to_the_float_projection_and_need_the_int8_matrix():
    n = 64896 // 16
    fast = P.BinaryProjector(input_dim=n, seed=3, matrix_dtype="int8", feature_bits=7)
    f = np.random.default_rng(4).standard_normal(n).astype(np.float32)
    ref = f.astype(np.float64) @ fast.matrix_float32().astype(np.float64)
    # rounding each feature by at most half a step s_f / 2 moves d_j by ~ s_f/2 sqrt(n/3) |q| s_P:
    # a few per cent of d's spread, so most bits survive (the measured share on real features:
    # docs/performance.md)
    shared = len(set(fast.bits(f).tolist()) & set(P.slsbh(ref).tolist()))
    assert shared >= 0.9 * 512
    assert np.corrcoef(fast.project(f), ref)[0, 1] > 0.99
    for bad in ({"matrix_dtype": "float32"}, {"matrix_dtype": "float16"}, {"projection": "sparse"},
                {"matrix_dtype": "int8", "input_dim": 140000}):
        with pytest.raises(ValueError, match="feature_bits 7"):
            P.ProjectorConfig(feature_bits=7, **bad)


def test_bin_import_with_int8_storage(tmp_path):
    m = PM.gaussian_matrix(40, seed=1)
    path = tmp_path / "randomMatrix.bin"
    W.save_bin(m, path)
    bp = P.BinaryProjector(input_dim=40, matrix_path=str(path), matrix_dtype="int8")
    generated = P.BinaryProjector(input_dim=40, seed=1, matrix_dtype="int8")
    # the same draws through the file or the seed give the same rounded matrix
    np.testing.assert_array_equal(bp.matrix, generated.matrix)
    assert bp.matrix_scale == generated.matrix_scale
    out = tmp_path / "exported.bin"
    W.save_bin(bp.matrix_float32(), out)  # export stays float32, with the rounded values
    np.testing.assert_array_equal(W.load_bin(out, 40), bp.matrix_float32())


# ------------------------------------------------------------------ B in torch on a device

def _marginal_only(bits_a, bits_b, d, k=256):
    """Every bit on which two sLSBH codes of (nearly) the same d differ must be marginal: its
    component within float32 rounding of the k-th largest / smallest value of d (a different
    summation order moves each d_j by ~1e-6 relative, so only near-ties can swap)."""
    diff = set(bits_a.tolist()) ^ set(bits_b.tolist())
    hi, lo = np.sort(d)[-k], np.sort(d)[k - 1]
    tol = 1e-4 * float(np.abs(d).max())
    for bit in diff:
        j = bit % d.shape[0]
        edge = hi if bit < d.shape[0] else lo
        assert abs(float(d[j]) - float(edge)) <= tol, (bit, d[j], edge)
    return len(diff)


def test_torch_projection_on_cpu_gives_the_numba_bits_up_to_marginal_ties():
    bp = P.BinaryProjector(input_dim=3000, seed=4)
    tp = P.TorchProjection(bp, "cpu")
    F = np.random.default_rng(7).standard_normal((12, 3000)).astype(np.float32)
    d = bp.project(F)
    flipped = 0
    for row, a, b in zip(d, bp.bits_batch(F), tp.bits_batch(F), strict=True):
        assert b.dtype == np.uint16 and b.size == 512 and np.all(np.diff(b.astype(int)) > 0)
        flipped += _marginal_only(a, b, row)
    assert flipped <= 12 * 4  # a few near-ties at most, never a systematic difference
    # the torch path's own sLSBH follows the definition (stable: ties to the lower index)
    import torch

    dt = (torch.from_numpy(F[0]) @ tp.matrix).numpy()
    np.testing.assert_array_equal(tp.bits_batch(F[:1])[0], P.slsbh(dt))
    # frame by frame, whatever the batch
    np.testing.assert_array_equal(np.stack(tp.bits_batch(F[3:5])), np.stack(tp.bits_batch(F)[3:5]))


def test_torch_projection_with_int8_storage_uses_the_rounded_matrix():
    # the device path multiplies the (unrounded) features by the values s_P q; against the CPU's
    # exact integer path, only near-ties may differ (the features' 16-bit rounding moves d_j by
    # ~1e-5 of max|d|, within _marginal_only's tolerance)
    bp = P.BinaryProjector(input_dim=3000, seed=4, matrix_dtype="int8")
    tp = P.TorchProjection(bp, "cpu")
    np.testing.assert_array_equal(tp.matrix.numpy(), bp.matrix_float32())
    F = np.random.default_rng(9).standard_normal((8, 3000)).astype(np.float32)
    d = F.astype(np.float64) @ bp.matrix_float32().astype(np.float64)
    flipped = sum(_marginal_only(a, b, row) for row, a, b in zip(d, bp.bits_batch(F), tp.bits_batch(F), strict=True))
    assert flipped <= 8 * 4


def test_torch_projection_uses_the_float16_rounded_matrix_and_centres_like_numba():
    bp = P.BinaryProjector(input_dim=500, seed=2, matrix_dtype="float16", centre_window=3)
    ref = P.BinaryProjector(input_dim=500, seed=2, matrix_dtype="float16", centre_window=3)
    tp = P.TorchProjection(bp, "cpu")
    np.testing.assert_array_equal(tp.matrix.numpy(), ref.matrix_float32())
    F = np.random.default_rng(8).standard_normal((6, 500)).astype(np.float32) + 3.0
    tp.bits_batch(F)
    ref.bits_batch(F)
    st = tp.state_dict()
    assert st["n_seen"] == 6
    np.testing.assert_allclose(st["mean"], ref.mean, rtol=0, atol=1e-12)
    other = P.TorchProjection(P.BinaryProjector(input_dim=500, seed=2, matrix_dtype="float16", centre_window=3), "cpu")
    other.load_state_dict(st)
    G = F[::-1].copy()
    for a, b in zip(tp.bits_batch(G), other.bits_batch(G), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="NaN"):
        tp.bits_batch(np.full((1, 500), np.nan, np.float32))


def test_device_field_accepts_cpu_auto_cuda_and_cuda_n_only():
    for dev in ("cpu", "auto", "cuda", "cuda:1"):
        assert P.ProjectorConfig(device=dev).device == dev
    with pytest.raises(ValueError):
        P.ProjectorConfig(device="gpu")


def test_a_gpu_device_fuses_a_and_b_into_one_node_in_the_plan():
    from neoslam_stream.config import load_config
    from neoslam_stream.nodes.pipelines import build_plan

    names = [s.name for s in build_plan(load_config("default")).stages]
    assert names[:2] == ["A", "B"]  # default: B is the numba kernel in its own process
    cfg = load_config("default", overrides={"projector": {"device": "cuda:1"}})
    stages = build_plan(cfg).stages
    assert [s.name for s in stages][:2] == ["A", "C"]
    assert stages[0].params["call"] == "codes_on_device"
    assert stages[0].params["features"]["device"] == "cuda:1"  # A follows B's device
    cfg = load_config("default", overrides={"projector": {"device": "cuda"}, "features": {"device": "cpu"}})
    with pytest.raises(ValueError, match="share the device"):
        build_plan(cfg)


def test_fused_node_on_cpu_emits_the_bits_of_a_then_b():
    feats = dict(backbone="random_alexnet", seed=1, device="cpu", frame_stride=2)
    fused = make_node("codes_on_device", features=feats, projector=dict(input_dim=64896, seed=5))
    fused.setup()
    a = make_node("features", features=feats)
    a.setup()
    b = b_node(input_dim=64896, seed=5)
    b.setup()
    rng = np.random.default_rng(0)
    msgs = [Message("image", i, i * 0.1, {"image": rng.integers(0, 256, (60, 80, 3), dtype=np.uint8),
                                          "encoding": "rgb8"}) for i in range(4)]
    out = fused.process_batch("image", msgs)
    assert [m.frame for _, m in out] == [0, 2] and fused.counters["strided"] == 2
    ref = b.process_batch("visual_features", [m for _, m in a.process_batch("image", msgs)])
    for (_, got), (_, want), (_, f) in zip(out, ref, a.process_batch("image", msgs), strict=True):
        assert got.type == "bin_features" and got["size"] == 2048
        _marginal_only(want["bits"], got["bits"], b.core.projector.project(f["features"]))
