"""The bench's launch tally (``_CallCount``) against sizes computed here: the bytes a launch's
arrays hold (each array once per launch), a copy's read and write, and the memory bandwidth
measured by a copy, on every device present."""

import numpy as np
import pytest
import warp as wp

from warpskin.bench import _CallCount, memory_bandwidth_gbs

DEVICES = ["cpu"] + (["cuda"] if wp.is_cuda_available() else [])


@wp.kernel
def _axpy(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = a[i] * b[i] + out[i]


@pytest.mark.parametrize("device", DEVICES)
def test_bytes_are_the_arrays_a_launch_takes_once_each(device):
    n = 37
    a = wp.array(np.ones((n, 3), dtype=np.float32), dtype=wp.vec3, device=device)
    b = wp.array(np.full(n, 2.0, dtype=np.float32), device=device)
    out = wp.zeros(n, dtype=wp.vec3, device=device)
    with _CallCount(device) as tally:
        wp.launch(_axpy, dim=n, inputs=[a, b], outputs=[out], device=device)
        wp.launch(_axpy, n, [out, b], [out], device=device)  # one array as input and output: once
        wp.copy(out, a, count=5)  # five vec3 read and written
        host = out.numpy()
    assert tally.launches == 3 and tally.readbacks == 1
    assert tally.bytes == (n * 12 + n * 4 + n * 12) + (n * 12 + n * 4) + 2 * 5 * 12
    np.testing.assert_allclose(host[:5], 1.0)  # the launches ran as given
    np.testing.assert_allclose(host[5:], 6.0)


@pytest.mark.parametrize("device", DEVICES)
def test_the_tally_restores_warp_and_the_bandwidth_is_measured(device):
    launch, copy, numpy = wp.launch, wp.copy, wp.array.numpy
    with _CallCount(device):
        assert wp.launch is not launch
    assert (wp.launch, wp.copy, wp.array.numpy) == (launch, copy, numpy)
    assert memory_bandwidth_gbs(device, mib=8, repeat=2) > 0.1  # any machine moves more than this
