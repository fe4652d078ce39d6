import errno
import os
import runpy
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from ruslam.data import teacher_cache
from ruslam.data.teacher_cache import TeacherCache, TeacherCacheError, build_cache
from ruslam.errors import InputError

# A tiny seeded teacher and dataset, shared by this process and the SIGKILLed child (same file, runpy).
FIXTURES = '''
import time
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from ruslam.models.pretrained import Teacher
from ruslam.models.pretrained.vlad import VLAD


class TinyLocal(nn.Module):
    descriptor_dim = 8

    def __init__(self, delay=0.0):
        super().__init__()
        torch.manual_seed(0)
        self.det, self.desc, self.delay, self.calls = nn.Conv2d(3, 65, 8, 8), nn.Conv2d(3, 8, 8, 8), delay, 0

    def forward(self, image):
        self.calls += len(image)
        time.sleep(self.delay)
        return {"keypoint_logits": 10 * self.det(image), "dense_descriptors": F.normalize(self.desc(image), dim=1)}


def tiny_teacher(delay=0.0):
    return Teacher(TinyLocal(delay), VLAD(num_clusters=4, dim=8, fit_images=4, fit_descriptors_per_image=40))


class Images:
    def __init__(self, n=10, broken=(), start=0):
        self.n, self.broken, self.start = n, set(broken), start

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        rng = np.random.default_rng(self.start + i)
        image = None if i in self.broken else rng.random((32, 48, 3)).astype(np.float32)
        return {"id": f"seq/{self.start + i:03d}", "image": image}
'''

CHILD_MAIN = '''
if __name__ == "__main__":
    import sys
    from ruslam.data.teacher_cache import build_cache
    build_cache(Images(24), tiny_teacher(delay=0.15), sys.argv[1], commit_every=3)
'''


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    path = tmp_path_factory.mktemp("fx") / "fixtures.py"
    path.write_text(FIXTURES + CHILD_MAIN)
    return runpy.run_path(str(path)) | {"path": path}


def teacher_outputs(teacher, image):
    with torch.no_grad():
        out = teacher(torch.from_numpy(image).permute(2, 0, 1)[None])
    return {k: v[0].numpy() for k, v in out.items()}


def assert_cache_equals_teacher(cache, teacher, dataset, atol):
    for i in range(len(dataset)):
        item = dataset[i]
        assert item["id"] in cache
        got, want = cache.read(item["id"]), teacher_outputs(teacher, item["image"])
        assert set(got) == {"keypoint_logits", "dense_descriptors", "global_descriptor"}
        for key in want:
            assert got[key].dtype == np.float32 and got[key].shape == want[key].shape
            np.testing.assert_allclose(got[key], want[key], atol=atol * np.abs(want[key]).max(), rtol=atol)


def no_temp_files(cache_dir: Path) -> bool:
    return not list(cache_dir.glob(".tmp-*"))


def test_round_trip_float16_and_float32(fx, tmp_path):
    dataset, teacher = fx["Images"](6), fx["tiny_teacher"]()
    cache = build_cache(dataset, teacher, tmp_path / "f16", float16=True, commit_every=4)
    assert len(cache) == 6 and len(list((tmp_path / "f16").glob("shard-*.h5"))) == 2
    assert list((tmp_path / "f16").glob("vlad_codebook_k4_seed0.npy")), "codebook saved beside the cache"
    assert_cache_equals_teacher(cache, teacher, dataset, atol=1e-3)
    for shard in (tmp_path / "f16").glob("shard-*.h5"):
        with h5py.File(shard) as f:
            assert f.id.get_create_plist().get_version()[0] == 3  # superblock v3: written with libver="latest"
            assert f.attrs["teacher_fingerprint"] == cache.fingerprint
            for name in f:  # one group per image (id with "/" escaped), one chunked compressed dataset per key
                assert name.startswith("seq%2F") and f[name].attrs["id"] == name.replace("%2F", "/")
                ds = f[name]["dense_descriptors"]
                assert ds.dtype == np.float16 and ds.compression == "lzf" and ds.chunks == ds.shape
    cache32 = build_cache(dataset, fx["tiny_teacher"](), tmp_path / "f32", float16=False, compression="gzip")
    assert_cache_equals_teacher(cache32, teacher, dataset, atol=1e-6)
    assert "seq/999" not in cache32
    with pytest.raises(KeyError, match="'seq/999' is not in the teacher cache"):
        cache32.read("seq/999")


def test_rerun_skips_cached_ids_and_extends(fx, tmp_path):
    build_cache(fx["Images"](5), fx["tiny_teacher"](), tmp_path)
    again = fx["tiny_teacher"]()
    build_cache(fx["Images"](5), again, tmp_path)
    assert again.local.calls == 0
    more = fx["tiny_teacher"]()
    cache = build_cache(fx["Images"](8), more, tmp_path)
    assert len(cache) == 8
    calls_without_codebook_fit = more.local.calls
    assert calls_without_codebook_fit == 3  # the codebook beside the cache is reused, only 3 new images run
    other = fx["tiny_teacher"]()  # fewer images than cached, but other ids: they are computed, not skipped
    cache = build_cache(fx["Images"](3, start=20), other, tmp_path)
    assert other.local.calls == 3 and len(cache) == 11 and "seq/022" in cache


def test_other_teacher_configuration_is_refused(fx, tmp_path):
    build_cache(fx["Images"](3), fx["tiny_teacher"](), tmp_path, config={"height": 32})
    with pytest.raises(ValueError, match="built by another teacher configuration"):
        build_cache(fx["Images"](3), fx["tiny_teacher"](), tmp_path, config={"height": 64})
    other = fx["tiny_teacher"]()
    with torch.no_grad():
        other.local.det.bias.add_(1.0)
    with pytest.raises(ValueError, match="built by another teacher configuration"):
        build_cache(fx["Images"](3), other, tmp_path, config={"height": 32})
    with pytest.raises(ValueError, match="built by another teacher configuration"):
        TeacherCache(tmp_path, fingerprint="0" * 64)


def test_unreadable_image_is_named_and_leaves_a_valid_cache(fx, tmp_path):
    message = r"Image 'seq/002' is unreadable: expected a finite HxWx3 array, got NoneType"
    with pytest.raises(InputError, match=message):  # met while fitting the VLAD codebook: the same type and sentence
        build_cache(fx["Images"](4, broken={2}), fx["tiny_teacher"](), tmp_path)
    build_cache(fx["Images"](4), fx["tiny_teacher"](), tmp_path, commit_every=2)
    with pytest.raises(InputError, match=message.replace("002", "005")):  # met while caching
        build_cache(fx["Images"](7, broken={5}), fx["tiny_teacher"](), tmp_path, commit_every=2)
    assert no_temp_files(tmp_path)
    assert len(TeacherCache(tmp_path)) == 4  # image 4 was in the uncommitted shard: dropped, recomputed below
    teacher = fx["tiny_teacher"]()
    cache = build_cache(fx["Images"](7), teacher, tmp_path, commit_every=2)
    assert_cache_equals_teacher(cache, teacher, fx["Images"](7), atol=1e-3)


def test_disk_full_stops_with_one_sentence_and_no_corrupt_file(fx, tmp_path, monkeypatch):
    real_write, calls = teacher_cache._write_group, []

    def write_until_full(*args, **kwargs):
        calls.append(1)
        if len(calls) == 4:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(*args, **kwargs)

    monkeypatch.setattr(teacher_cache, "_write_group", write_until_full)
    with pytest.raises(TeacherCacheError, match="stopped because the disk is full"):
        build_cache(fx["Images"](6), fx["tiny_teacher"](), tmp_path, commit_every=2)
    assert no_temp_files(tmp_path) and len(TeacherCache(tmp_path)) == 2
    monkeypatch.setattr(teacher_cache, "_write_group", real_write)
    teacher = fx["tiny_teacher"]()
    cache = build_cache(fx["Images"](6), teacher, tmp_path, commit_every=2)
    assert_cache_equals_teacher(cache, teacher, fx["Images"](6), atol=1e-3)


def test_sigkill_mid_run_then_rerun_equals_a_clean_run(fx, tmp_path):
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    child = subprocess.Popen([sys.executable, str(fx["path"]), str(killed)], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    def mid_shard():  # two shards committed and a third one being filled
        return len(list(killed.glob("shard-*.h5"))) >= 2 and list(killed.glob(".tmp-*.h5"))

    while not mid_shard() and time.time() < deadline and child.poll() is None:
        time.sleep(0.01)
    assert child.poll() is None, child.stderr.read().decode()[-2000:]
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    partial = TeacherCache(killed)
    assert 0 < len(partial) < 24  # killed mid-run
    assert list(killed.glob(".tmp-*.h5")), "the kill interrupted an uncommitted shard"

    rerun = build_cache(fx["Images"](24), fx["tiny_teacher"](), killed, commit_every=3)
    reference = build_cache(fx["Images"](24), fx["tiny_teacher"](), clean, commit_every=3)
    assert no_temp_files(killed) and len(rerun) == len(reference) == 24
    for i in range(24):
        image_id = f"seq/{i:03d}"
        got, want = rerun.read(image_id), reference.read(image_id)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key])


def test_a_bad_file_is_named_by_index_but_a_reader_bug_keeps_its_traceback(fx, tmp_path):
    class Failing(fx["Images"]):
        def __init__(self, error):
            super().__init__(4)
            self.error = error

        def __getitem__(self, i):
            if i == 3:
                raise self.error
            return super().__getitem__(i)

    with pytest.raises(TeacherCacheError, match=r"Image 3 of the dataset could not be read \(x.png is corrupt\)"):
        teacher_cache.missing_indices(Failing(InputError("x.png is corrupt")), set())
    with pytest.raises(KeyError, match="depth"):
        teacher_cache.missing_indices(Failing(KeyError("depth")), set())
