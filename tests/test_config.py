from dataclasses import dataclass

import pytest

from taichi_gs.config import read_config, to_toml, write_config
from taichi_gs.errors import InputError


@dataclass(frozen=True)
class Demo:
    iterations: int = 10
    rate: float = 0.5
    name: str = "a"
    flag: bool = True
    sizes: tuple = (1, 2)


def test_toml_round_trip(tmp_path):
    sections = {"demo": Demo(iterations=3, rate=1e-4, name='q"x', flag=False, sizes=(4, 5))}
    write_config(tmp_path / "c.toml", sections)
    assert read_config(tmp_path / "c.toml", {"demo": Demo()}) == sections


def test_int_accepted_for_float_and_unknown_keys_rejected(tmp_path):
    (tmp_path / "c.toml").write_text("[demo]\nrate = 2\n")
    assert read_config(tmp_path / "c.toml", {"demo": Demo()})["demo"].rate == 2.0
    (tmp_path / "c.toml").write_text("[demo]\nrat = 2\n")
    with pytest.raises(InputError, match="unknown key 'rat'"):
        read_config(tmp_path / "c.toml", {"demo": Demo()})
    (tmp_path / "c.toml").write_text("[demo]\niterations = 'many'\n")
    with pytest.raises(InputError, match="must be int"):
        read_config(tmp_path / "c.toml", {"demo": Demo()})


def test_to_toml_text():
    assert to_toml({"demo": Demo()}).splitlines()[:3] == ["[demo]", "iterations = 10", "rate = 0.5"]
