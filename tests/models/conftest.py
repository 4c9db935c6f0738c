import pytest
import torch


@pytest.fixture
def one_thread():
    """One torch thread for the test, restored after it: on a shared 2-core machine the many small operations of a
    training step (SCNN's slice convolutions, a transformer's attention) run several times faster on one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
