"""Shared fixtures: small random map sets with a fixed seed."""

from __future__ import annotations

import pytest
import torch

from matscan.mapset import MapSet


def random_maps(size: int = 16, seed: int = 0, dtype: torch.dtype = torch.float32, tilt: float = 0.3) -> MapSet:
    g = torch.Generator().manual_seed(seed)
    normal = torch.randn(3, size, size, generator=g, dtype=dtype) * tilt
    normal[2] = 1.0
    normal = normal / normal.norm(dim=0, keepdim=True)
    return MapSet(
        diffuse=torch.rand(3, size, size, generator=g, dtype=dtype),
        specular=torch.rand(3, size, size, generator=g, dtype=dtype) * 0.5 + 0.02,
        roughness=torch.rand(1, size, size, generator=g, dtype=dtype) * 0.8 + 0.15,
        normal=normal,
    )


@pytest.fixture
def maps() -> MapSet:
    return random_maps()
