import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    # Tiny batches: intra-op threads only add wake-up latency on a busy 2-core machine
    # (the kinematic scripted test ran 4 s with 2 threads, 1.3 s with 1).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
