"""The command line: real --help for every command, one-line errors with exit code != 0."""

import subprocess
import sys

import pytest

COMMANDS = ["generate", "train", "evaluate", "export", "serve", "devices", "demo", "import", "import tignn"]


def thermognn(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "thermognn.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


@pytest.mark.parametrize("command", COMMANDS)
def test_help(command):
    res = thermognn(*command.split(), "--help")
    assert res.returncode == 0, res.stderr
    assert "Usage" in res.stdout and len(res.stdout.splitlines()) > 5


def one_line_error(res, *needles):
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert "Traceback" not in res.stderr


def test_unknown_config_key(tmp_path):
    one_line_error(thermognn("train", "train.no_such_key=3", f"out={tmp_path}"), "train.no_such_key")


def test_unknown_config_group_option(tmp_path):
    one_line_error(thermognn("generate", "scene=no_such_scene", f"out={tmp_path}"), "no_such_scene")


def test_missing_dataset(tmp_path):
    one_line_error(thermognn("train", f"out={tmp_path}"), "dataset.h5", "not found")
    assert list(tmp_path.iterdir()) == []  # nothing partial left behind


def test_corrupt_dataset(tmp_path):
    (tmp_path / "dataset.h5").write_bytes(b"\x00garbage")
    one_line_error(thermognn("train", f"out={tmp_path}"), "dataset.h5", "HDF5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dataset.h5"]


def test_missing_checkpoint_and_model(tmp_path):
    one_line_error(thermognn("export", f"out={tmp_path}"), "model.ckpt")
    one_line_error(thermognn("serve", "--duration", "1", f"out={tmp_path}"), "model.pt")


def test_unknown_device(tmp_path):
    one_line_error(thermognn("serve", "--device", "no_such_device", "--duration", "1", f"out={tmp_path}"),
                   "no_such_device")


def test_devices_lists_plugins():
    res = thermognn("devices")
    assert res.returncode == 0, res.stderr
    for name in ("sim", "replay", "geomagic", "senseglove"):
        assert name in res.stdout
