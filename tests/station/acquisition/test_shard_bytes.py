"""The run store's own shard and metadata writer: its bytes on disk equal those of
the first format-2 implementation, every inner chunk and per-frame record equals what zarr
itself writes, for random uint8 and uint16 frames with aligned and padded edges, and plain
zarr reads them back."""

import google_crc32c
import numpy as np
import pytest
import zarr
from zarr.codecs import BytesCodec, Crc32cCodec

from station.acquisition.patterns import StationPatternPlan
from station.acquisition.run_store import META_ARRAYS, FrameMeta, RunStore

LCD = (24, 16)
PLAN = StationPatternPlan.for_lcd(LCD, 4, 3)
N = 3  # frames written per case


def reference_shard(image: np.ndarray, tile: int) -> bytes:
    """The shard as the first format-2 writer built it: pad to whole chunks with 0, transpose
    into (chunk row, chunk col, tile, tile), each chunk's bytes then its crc32c, then the index
    of (offset, nbytes) uint64 and the index's crc32c."""
    h, w = image.shape
    nr, nc = -(-h // tile), -(-w // tile)
    padded = np.zeros((nr * tile, nc * tile), image.dtype.newbyteorder("<"))
    padded[:h, :w] = image
    chunks = padded.reshape(nr, tile, nc, tile).transpose(0, 2, 1, 3).reshape(nr * nc, -1)
    body, index = b"", []
    for c in chunks:
        data = np.ascontiguousarray(c).tobytes()
        index.append((len(body), len(data) + 4))
        body += data + np.uint32(google_crc32c.value(data)).astype("<u4").tobytes()
    idx = np.asarray(index, "<u8").tobytes()
    return body + idx + np.uint32(google_crc32c.value(idx)).astype("<u4").tobytes()


def meta(p: int) -> FrameMeta:
    return FrameMeta(stage_target_mm=1.5, stage_measured_mm=1.5 + 1e-4 * p, swap_index=p,
                     swap_time_s=3.25 + p, camera_timestamp_s=7.5 + p, frame_id=40 + p,
                     exposure_ms=12.5, retries=p % 2)


@pytest.mark.parametrize(("dtype", "bits", "camera_size", "tile"), [
    (np.uint16, 12, (20, 13), 8),   # partial edge chunks in both directions
    (np.uint16, 16, (48, 40), 8),   # aligned
    (np.uint8, 8, (64, 37), 16),    # aligned width, partial height
    (np.uint8, 6, (30, 32), 16),    # partial width, aligned height
])
def test_shards_and_records_equal_the_reference_and_zarr(tmp_path, dtype, bits, camera_size,
                                                         tile):
    w, h = camera_size
    full = 2**bits - 1
    rng = np.random.default_rng(bits * 1000 + w)
    imgs = [rng.integers(0, full + 1, (h, w)).astype(dtype) for _ in range(N)]
    imgs[1][: h // 2] = full  # saturated pixels, counted
    s = RunStore.create(tmp_path / "run.zarr", config={}, plan=PLAN, depths_mm=[1.5],
                        camera_size=camera_size, bit_depth=bits, lcd_size=LCD,
                        lcd_pitch_mm=0.25, tile_px=tile)
    for p, img in enumerate(imgs):
        s.write_frame(0, p, img[::1, :] if p != 2 else np.asfortranarray(img), meta(p))

    # the same frames and records written by zarr itself, with the store's codecs
    g = zarr.open_group(str(tmp_path / "ref.zarr"), mode="w", zarr_format=3)
    n = len(PLAN)
    ref = g.create_array("frames", shape=(1, n, h, w), shards=(1, 1, -(-h // tile) * tile,
                         -(-w // tile) * tile), chunks=(1, 1, tile, tile), dtype=dtype,
                         fill_value=0, serializer=BytesCodec(endian="little"),
                         compressors=[Crc32cCodec()])
    for p, img in enumerate(imgs):
        ref[0, p] = img
    for p, img in enumerate(imgs):
        ours = (s.path / "frames" / "c" / "0" / str(p) / "0" / "0").read_bytes()
        assert ours == reference_shard(img, tile)
        theirs = (tmp_path / "ref.zarr" / "frames" / "c" / "0" / str(p) / "0" / "0").read_bytes()
        assert len(ours) == len(theirs)
        # zarr 3.1 lays the chunks out in Morton order, the store in row-major order (a row of
        # tiles is one read); each chunk (pixels + crc32c) is the same bytes, found by the index
        n_chunks = -(-h // tile) * -(-w // tile)
        idx_ours, idx_theirs = (np.frombuffer(b[-(16 * n_chunks + 4):-4], "<u8").reshape(-1, 2)
                                for b in (ours, theirs))
        for (o1, n1), (o2, n2) in zip(idx_ours, idx_theirs, strict=True):
            assert n1 == n2 and ours[o1 : o1 + n1] == theirs[o2 : o2 + n2]
    plain = zarr.open_group(str(s.path), mode="r")
    np.testing.assert_array_equal(plain["frames"][0, :N], np.stack(imgs))
    assert not plain["done"][0, N:].any() and plain["done"][0, :N].all()

    want = {name: [] for name in META_ARRAYS}
    for p, img in enumerate(imgs):
        for k, v in meta(p).model_dump().items():
            want[k].append(v)
        want["saturated_px"].append(int(np.count_nonzero(img == full)))
        want["frame_crc32c"].append(google_crc32c.value(img.astype(img.dtype.newbyteorder("<"))
                                                        .tobytes()))
    for name, values in want.items():
        arr = plain[name]
        np.testing.assert_array_equal(arr[0, :N], values)
        r = g.create_array(name, shape=arr.shape, chunks=arr.chunks, dtype=arr.dtype,
                           fill_value=arr.fill_value, compressors=None)
        r[0, :N] = values
        assert (s.path / name / "c" / "0" / "0").read_bytes() == \
            (tmp_path / "ref.zarr" / name / "c" / "0" / "0").read_bytes(), name
    r = g.create_array("done", shape=(1, n), chunks=(1, n), dtype="bool", fill_value=False,
                       compressors=None)
    r[0, :N] = True
    assert (s.path / "done" / "c" / "0" / "0").read_bytes() == \
        (tmp_path / "ref.zarr" / "done" / "c" / "0" / "0").read_bytes()
    for p, img in enumerate(imgs):
        np.testing.assert_array_equal(RunStore.open(s.path).read_frame(0, p), img)


def test_a_damaged_record_chunk_is_refused_on_write(tmp_path):
    s = RunStore.create(tmp_path / "run.zarr", config={}, plan=PLAN, depths_mm=[1.5],
                        camera_size=(20, 13), bit_depth=12, lcd_size=LCD, lcd_pitch_mm=0.25,
                        tile_px=8)
    img = np.zeros((13, 20), np.uint16)
    s.write_frame(0, 0, img, meta(0))
    chunk = s.path / "frame_id" / "c" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:-3])
    with pytest.raises(Exception, match=r"chunk frame_id/c/0/0 has \d+ bytes, expected"):
        s.write_frame(0, 1, img, meta(1))
    assert not s.done()[0, 1]
