"""Copies between NumPy and device ndarrays (taichi_gs.kernels.host_copy): on the CPU backend they go
through a view of the ndarray's memory, so they must agree with Taichi's own copies for every element
type and layout the package uses, see what a kernel wrote, and be seen by the next kernel."""

import numpy as np
import pytest
import taichi as ti

from taichi_gs.kernels import host_copy, runtime


@pytest.fixture(autouse=True)
def cpu_backend():
    runtime.init("cpu")


@pytest.mark.parametrize("dtype, shape", [(ti.f32, (7, 5, 3)), (ti.f64, (11, 4)), (ti.i32, (13,)),
                                          (ti.f32, (6, 1, 3))])
def test_write_and_read_agree_with_taichis_copies(dtype, shape) -> None:
    values = np.random.default_rng(0).normal(size=shape) * 100
    array = ti.ndarray(dtype, shape)
    host_copy.write(array, values)
    expected = values.astype(array.to_numpy().dtype)  # the same cast as Taichi's from_numpy
    np.testing.assert_array_equal(array.to_numpy(), expected)
    np.testing.assert_array_equal(host_copy.read(array), expected)
    np.testing.assert_array_equal(host_copy.read(array, 3), expected[:3])
    assert host_copy.read(array).dtype == array.to_numpy().dtype


def test_vector_ndarray_elements_come_last() -> None:
    array = ti.Vector.ndarray(3, ti.f32, (4,))
    values = np.arange(12, dtype=np.float32).reshape(4, 3)
    array.from_numpy(values)
    np.testing.assert_array_equal(host_copy.read(array), values)
    host_copy.write(array, values[::-1])
    np.testing.assert_array_equal(array.to_numpy(), values[::-1])


def test_a_read_is_a_copy_that_sees_kernel_writes() -> None:
    @ti.kernel
    def add_one(a: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        for i, j in a:
            a[i, j] += 1.0

    array = ti.ndarray(ti.f32, (64, 48))
    host_copy.write(array, np.zeros((64, 48)))
    before = host_copy.read(array)
    add_one(array)
    after = host_copy.read(array)
    np.testing.assert_array_equal(before, 0.0)  # not a view: the kernel did not change it
    np.testing.assert_array_equal(after, 1.0)
    host_copy.write(array, np.full((64, 48), 5.0))
    add_one(array)
    np.testing.assert_array_equal(array.to_numpy(), 6.0)


def test_a_write_of_the_wrong_size_is_refused() -> None:
    array = ti.ndarray(ti.f32, (4, 3))
    with pytest.raises(ValueError, match=r"\(4, 3\)"):
        host_copy.write(array, np.zeros(13))
    host_copy.write(array, np.ones(12))  # any shape with as many elements
    np.testing.assert_array_equal(array.to_numpy(), 1.0)
