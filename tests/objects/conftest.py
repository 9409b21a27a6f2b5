import numpy as np
import pytest

from _assets import simple_bowl
from keygen.objects.asset import Asset, ConvexPart


@pytest.fixture
def bowl_asset() -> Asset:
    return simple_bowl()


@pytest.fixture
def capsule_part() -> ConvexPart:
    return ConvexPart("capsule", p0=np.array([0, 0, 0.0]), p1=np.array([0.1, 0, 0]), radius=0.01)
