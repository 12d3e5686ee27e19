import pytest
import torch

torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture(scope="session")
def toy_data():
    from torchrl_offhrl.data import make_toy_dataset

    return make_toy_dataset(num_episodes=40, episode_length=25, seed=0)


@pytest.fixture(scope="session")
def fitted_ensemble(toy_data):
    """A small ensemble fitted on the toy linear dynamics (actions in [-0.5, 0.5])."""
    from torchrl_offhrl.models import DynamicsEnsemble

    torch.manual_seed(0)
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=5, hidden_sizes=(64, 64))
    ens.fit(toy_data, lr=1e-3, batch_size=128, max_epochs=60, patience=10, progress=False)
    return ens


@pytest.fixture(scope="session")
def fitted_cvae(toy_data):
    from torchrl_offhrl.models import ConditionalVAE

    torch.manual_seed(0)
    return ConditionalVAE.for_dataset(toy_data, hidden_sizes=(64, 64)).fit(
        toy_data, lr=1e-3, max_epochs=20, progress=False
    )
