from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from gpomap.errors import InputFormatError
from gpomap.grid import FREE, OCCUPIED, UNKNOWN, GridSpec, OccupancyMap
from gpomap.io import atomic
from gpomap.io.rosmap import read_map_image, read_rosmap, write_rosmap

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TURTLEBOT = DATA / "turtlebot3-world-map" / "map.yaml"


def _write_map(directory, image_name="map.pgm", **overrides):
    """A small valid map: 3 rows x 4 cols, top row occupied, middle unknown, bottom free."""
    config = {
        "image": image_name,
        "resolution": 0.1,
        "origin": [1.5, -2.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    config.update(overrides)
    config = {k: v for k, v in config.items() if v is not None}
    pixels = np.array([[0, 0, 0, 0], [205, 205, 205, 205], [254, 254, 254, 128]], dtype=np.uint8)
    if image_name.endswith(".pgm"):
        (directory / image_name).write_bytes(b"P5\n# comment\n4 3\n255\n" + pixels.tobytes())
    path = directory / "map.yaml"
    path.write_text(yaml.safe_dump(config))
    return path, pixels


def _sample_map():
    grid = GridSpec((-3.25, 0.75), 0.05, (7, 9))
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, grid.shape)
    return OccupancyMap(grid, p, variance=rng.uniform(0, 1, grid.shape))


# ------------------------------------------------------------------ reading


@pytest.mark.skipif(not TURTLEBOT.exists(), reason=f"shared data missing: {TURTLEBOT}")
def test_turtlebot_map():
    m = read_rosmap(TURTLEBOT)
    assert m.grid.shape == (384, 384)
    assert m.grid.resolution == 0.05
    assert m.grid.origin == (-10.0, -10.0)
    assert (m.mode, m.negate, m.yaw) == ("trinary", False, 0.0)
    assert (m.free_thresh, m.occupied_thresh) == (0.196, 0.65)
    assert m.occupied.sum() == np.count_nonzero(m.pixels == 0) == 795
    assert m.free.sum() == np.count_nonzero(m.pixels == 254) == 7939
    assert m.unknown.sum() == np.count_nonzero(m.pixels == 205) == 384 * 384 - 795 - 7939
    # Row 0 is the lowest y: the image's bottom row.
    top_down = np.asarray(Image.open(TURTLEBOT.parent / "map.pgm"))
    np.testing.assert_array_equal(m.pixels, top_down[::-1])
    om = m.to_occupancy_map()
    np.testing.assert_array_equal(om.ternary, m.ternary)


def test_small_pgm_orientation_and_labels(tmp_path):
    path, _ = _write_map(tmp_path)
    m = read_rosmap(path)
    assert m.grid == GridSpec((1.5, -2.0), 0.1, (3, 4))
    # Image top row (occupied) is the map's highest row.
    assert m.occupied[2].all() and not m.occupied[:2].any()
    assert m.free[0, :3].all() and m.unknown[0, 3]  # 128 -> p = 0.498, between thresholds
    np.testing.assert_allclose(m.probability[0, 0], 1 / 255)
    assert m.image_path == tmp_path / "map.pgm"


def test_negate(tmp_path):
    path, _ = _write_map(tmp_path, negate=1)
    m = read_rosmap(path)
    assert m.free[2].all()  # black is free with negate 1
    assert m.occupied[0, :3].all()


def test_plain_pgm_p2_with_maxval_15(tmp_path):
    path, _ = _write_map(tmp_path)
    (tmp_path / "map.pgm").write_text("P2\n# plain\n2 2 # size\n15\n0 15\n 15 0\n")
    m = read_rosmap(path)
    # Stretched to 0..255 and flipped.
    np.testing.assert_array_equal(m.pixels, [[255, 0], [0, 255]])


def test_png_rgba_scale_mode_transparency(tmp_path):
    rgba = np.zeros((2, 3, 4), dtype=np.uint8)
    rgba[..., :3] = 254
    rgba[..., 3] = 255
    rgba[0, 0] = (0, 0, 0, 255)
    rgba[1, 2, 3] = 0  # transparent: unknown in scale mode
    Image.fromarray(rgba, "RGBA").save(tmp_path / "map.png")
    path, _ = _write_map(tmp_path, image_name="map.png", mode="scale")
    m = read_rosmap(path)
    assert m.grid.shape == (2, 3)
    assert m.occupied[1, 0] and m.occupied.sum() == 1
    assert m.unknown[0, 2] and m.unknown.sum() == 1
    assert m.free.sum() == 4
    assert np.isnan(m.to_occupancy_map().probability[0, 2])


def test_raw_mode(tmp_path):
    Image.fromarray(np.array([[0, 50, 100, 255]], dtype=np.uint8), "L").save(tmp_path / "map.png")
    path, _ = _write_map(tmp_path, image_name="map.png", mode="raw")
    m = read_rosmap(path)
    np.testing.assert_array_equal(m.probability[0, :3], [0.0, 0.5, 1.0])
    assert np.isnan(m.probability[0, 3])
    np.testing.assert_array_equal(m.ternary, [[FREE, UNKNOWN, OCCUPIED, UNKNOWN]])


def test_scientific_notation_strings_are_numbers(tmp_path):
    path, _ = _write_map(tmp_path)
    path.write_text(path.read_text().replace("resolution: 0.1", "resolution: 5e-2"))
    assert read_rosmap(path).grid.resolution == 0.05


# ------------------------------------------------------------------ malformed inputs


def test_missing_key(tmp_path):
    path, _ = _write_map(tmp_path, free_thresh=None)
    with pytest.raises(InputFormatError, match="missing the required key 'free_thresh'"):
        read_rosmap(path)


def test_yaml_not_a_mapping(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("- image: map.pgm\n- resolution: 0.05\n")
    with pytest.raises(InputFormatError, match=r"must be a mapping.*got list"):
        read_rosmap(path)


def test_image_not_pgm_or_png(tmp_path):
    path, _ = _write_map(tmp_path, image_name="map.jpg")
    (tmp_path / "map.jpg").write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00")
    with pytest.raises(InputFormatError, match=r"must be a PGM .* or PNG file, found a JPEG file"):
        read_rosmap(path)


def test_colour_ppm_is_named(tmp_path):
    path, _ = _write_map(tmp_path, image_name="map.ppm")
    (tmp_path / "map.ppm").write_bytes(b"P6\n1 1\n255\n\x00\x00\x00")
    with pytest.raises(InputFormatError, match="found a binary PPM"):
        read_rosmap(path)


def test_rotated_origin(tmp_path):
    path, _ = _write_map(tmp_path, origin=[0.0, 0.0, 0.5])
    with pytest.raises(InputFormatError, match=r"'origin' has yaw 0.5 .*rotated maps are not supported"):
        read_rosmap(path)


def test_missing_image(tmp_path):
    path, _ = _write_map(tmp_path)
    (tmp_path / "map.pgm").unlink()
    with pytest.raises(InputFormatError, match=r"image file 'map\.pgm' named by 'image' not found"):
        read_rosmap(path)


@pytest.mark.parametrize("value", [0, -0.05, "abc", ".nan"])
def test_bad_resolution_value(tmp_path, value):
    path, _ = _write_map(tmp_path)
    path.write_text(path.read_text().replace("resolution: 0.1", f"resolution: {value}"))
    with pytest.raises(InputFormatError, match="'resolution' must be"):
        read_rosmap(path)


def test_error_names_the_line(tmp_path):
    path, _ = _write_map(tmp_path, mode="fancy")
    with pytest.raises(InputFormatError, match=r"line \d+: 'mode' must be one of trinary, scale, raw") as info:
        read_rosmap(path)
    mode_line = [i for i, text in enumerate(path.read_text().splitlines(), 1) if text.startswith("mode:")]
    assert [info.value.line] == mode_line


def test_truncated_pgm(tmp_path):
    (tmp_path / "x.pgm").write_bytes(b"P5\n4 3\n255\n\x00\x00")
    with pytest.raises(InputFormatError, match="truncated"):
        read_map_image(tmp_path / "x.pgm")


def test_16_bit_pgm(tmp_path):
    (tmp_path / "x.pgm").write_bytes(b"P5\n1 1\n65535\n\x00\x00")
    with pytest.raises(InputFormatError, match="only 8-bit"):
        read_map_image(tmp_path / "x.pgm")


def test_missing_yaml(tmp_path):
    with pytest.raises(InputFormatError, match="not found"):
        read_rosmap(tmp_path / "nope.yaml")


# ------------------------------------------------------------------ writing


def test_round_trip_trinary(tmp_path):
    om = _sample_map()
    yaml_path, image_path = write_rosmap(om, tmp_path / "out.yaml")
    assert image_path == tmp_path / "out.pgm"
    m = read_rosmap(yaml_path)
    assert m.grid == om.grid
    np.testing.assert_array_equal(m.ternary, om.ternary)
    np.testing.assert_array_equal(m.to_occupancy_map().ternary, om.ternary)
    assert set(np.unique(m.pixels)) <= {0, 205, 254}
    # The paper's thresholds: occupied kept, free capped so that 205 reads as unknown.
    assert (m.free_thresh, m.occupied_thresh) == (0.196, 0.66)
    # Pillow (like ROS tools) opens the image: 8-bit grey, width x height.
    with Image.open(image_path) as img:
        assert (img.format, img.mode, img.size) == ("PPM", "L", (9, 7))


def test_round_trip_scale(tmp_path):
    om = _sample_map()
    om.probability[0, 0] = np.nan
    write_rosmap(om, tmp_path / "out.yaml", mode="scale")
    m = read_rosmap(tmp_path / "out.yaml")
    assert m.mode == "scale"
    assert m.grid == om.grid
    assert (m.free_thresh, m.occupied_thresh) == om.thresholds
    ok = np.isfinite(om.probability)
    assert np.abs(m.probability[ok] - om.probability[ok]).max() <= 0.5 / 255 + 1e-12
    assert m.ternary[0, 0] == UNKNOWN


def test_round_trip_awkward_geometry(tmp_path):
    grid = GridSpec((-1e-5, 123.456789012345), 1e-5, (2, 3))
    om = OccupancyMap(grid, np.full(grid.shape, 0.9))
    write_rosmap(om, tmp_path / "m.yaml")
    assert read_rosmap(tmp_path / "m.yaml").grid == grid


def test_write_rejects_bad_mode(tmp_path):
    with pytest.raises(ValueError, match="'trinary' or 'scale'"):
        write_rosmap(_sample_map(), tmp_path / "m.yaml", mode="raw")


@pytest.mark.parametrize("failing_call", [1, 2])
def test_interrupted_write_keeps_previous_files(tmp_path, monkeypatch, failing_call):
    yaml_path, image_path = write_rosmap(_sample_map(), tmp_path / "map.yaml")
    before = (yaml_path.read_bytes(), image_path.read_bytes())

    # Fail while committing: after the image temp (call 1) or both temps (call 2) were written.
    calls = []
    real_fsync = atomic.os.fsync

    def failing_fsync(fd):
        calls.append(fd)
        if len(calls) == failing_call:
            raise OSError("simulated disk failure")
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", failing_fsync)
    other = OccupancyMap(GridSpec((0, 0), 0.2, (20, 30)), np.zeros((20, 30)))
    with pytest.raises(OSError, match="simulated disk failure"):
        write_rosmap(other, yaml_path)
    assert (yaml_path.read_bytes(), image_path.read_bytes()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.pgm", "map.yaml"]


@pytest.mark.skipif(not TURTLEBOT.exists(), reason=f"shared data missing: {TURTLEBOT}")
def test_turtlebot_rewrite_is_identical_in_pixels(tmp_path):
    original = read_rosmap(TURTLEBOT)
    write_rosmap(original.to_occupancy_map(), tmp_path / "copy.yaml")
    copy = read_rosmap(tmp_path / "copy.yaml")
    assert copy.grid == original.grid
    assert (copy.free_thresh, copy.occupied_thresh) == (0.196, 0.65)
    np.testing.assert_array_equal(copy.pixels, original.pixels)


# ------------------------------------------------------------------ hostile input


def _yaml_with(tmp_path, key, text):
    """The small valid map, with `key`'s line replaced by raw YAML `text`."""
    path, _ = _write_map(tmp_path)
    lines = [f"{key}: {text}" if line.startswith(f"{key}:") else line for line in path.read_text().splitlines()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "value",
    ["1e400", "1.0e+400", ".nan", ".inf", "-0.1", "9" * 5000, "9" * 400, "[0.1]"],
    ids=["1e400", "1.0e+400", "nan", "inf", "negative", "5000-digits", "400-digits", "list"],
)
def test_bad_resolution(tmp_path, value):
    path = _yaml_with(tmp_path, "resolution", value)
    with pytest.raises(InputFormatError, match=r"map\.yaml(, line \d+)?: .*resolution") as info:
        read_rosmap(path)
    assert len(str(info.value)) < 400


def test_yaml_limits(tmp_path):
    path, _ = _write_map(tmp_path)
    path.write_text(path.read_text() + "# " + "x" * (1 << 20) + "\n")
    with pytest.raises(InputFormatError, match=r"map YAML is [\d,]+ bytes; expected a small text file \(at most 1,048,576"):
        read_rosmap(path)
    path.write_text("image: map.pgm\nextra: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(InputFormatError, match=r"map YAML nests 5000 levels"):
        read_rosmap(path)
    path.write_bytes(b"image: \xff\xfe\n")
    with pytest.raises(InputFormatError, match=r"map\.yaml, line 1: map YAML file is not UTF-8"):
        read_rosmap(path)


@pytest.mark.parametrize("name", ["a" * 300, "x\0y.pgm", "dir"])
def test_image_name_that_cannot_be_opened(tmp_path, name):
    (tmp_path / "dir").mkdir()
    path = _yaml_with(tmp_path, "image", yaml.safe_dump(name).splitlines()[0])
    with pytest.raises(InputFormatError, match=r"map\.yaml.*(cannot be looked up|not found|is a directory)") as info:
        read_rosmap(path)
    assert len(str(info.value)) < 500


def test_absurd_image_size_refused_from_the_header(tmp_path):
    # 20000 x 20000 announced by a 30-byte file: refused before any raster is read.
    (tmp_path / "big.pgm").write_bytes(b"P5\n20000 20000\n255\n" + bytes(10))
    with pytest.raises(InputFormatError, match=r"big\.pgm: map image is 20000 x 20000 = 400,000,000 pixels; at most 200,000,000"):
        read_map_image(tmp_path / "big.pgm")
    (tmp_path / "big2.pgm").write_bytes(b"P2\n5000 5000\n255\n0 0 0\n")
    with pytest.raises(InputFormatError, match=r"25,000,000 pixels; at most 20,000,000"):
        read_map_image(tmp_path / "big2.pgm")
    png = b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\x0dIHDR" + (30000).to_bytes(4, "big") * 2 + b"\x08\x00\x00\x00\x00"
    (tmp_path / "big.png").write_bytes(png)
    with pytest.raises(InputFormatError, match=r"big\.png: map image is 30000 x 30000 = 900,000,000 pixels"):
        read_map_image(tmp_path / "big.png")
    (tmp_path / "huge.pgm").write_bytes(b"P5\n" + b"9" * 5000 + b" 2\n255\n")
    with pytest.raises(InputFormatError, match=r"huge\.pgm.*PGM header: expected a number"):
        read_map_image(tmp_path / "huge.pgm")


def test_pillow_bomb_becomes_input_format_error(tmp_path):
    # 15000 x 13000 = 195 M pixels: under our limit, over Pillow's own (2 x 89 M).
    png = b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\x0dIHDR" + (15000).to_bytes(4, "big") + (13000).to_bytes(4, "big")
    (tmp_path / "bomb.png").write_bytes(png + b"\x08\x00\x00\x00\x00" + b"\x00" * 4 + b"\x00\x00\x00\x00IEND\xaeB`\x82")
    with pytest.raises(InputFormatError, match=r"bomb\.png: (PNG image refused as too large by Pillow|cannot decode PNG)"):
        read_map_image(tmp_path / "bomb.png")
