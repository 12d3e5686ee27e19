"""Acting in the CVAE's latent action space."""
from __future__ import annotations

import warnings

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded
from torchrl.envs.transforms import Compose, Transform

__all__ = ["DEFAULT_LATENT_BOUND", "AffineActionMap", "LatentActionTransform"]

#: the latent box's half-width where none is given (``model_env.latent_bound``): the CVAE prior N(0, 1) within 2 std
DEFAULT_LATENT_BOUND = 2.0


class AffineActionMap(torch.nn.Module):
    """The decoder discarded: the latent box ``[-latent_bound, latent_bound]^d`` mapped affinely onto the action box.

    The transfer setting's fine-tuning acts in real actions (the paper: "the
    decoder is discarded, and the agent is made to plan using the actual
    actions"). The agent's policy keeps its outputs (a tanh-squashed
    distribution on the latent box, ``latent_dim == action_dim``), and
    :class:`LatentActionTransform` with this map in place of the decoder
    turns them into actions: ``low + (z + b) / (2 b) * (high - low)``.

    Rescaling rather than clipping: the policy's whole output range stays
    usable (clipping a ``[-2, 2]`` box to ``[-1, 1]`` would put every latent
    beyond ``+-1`` on the box's faces, where the policy's log-probabilities no
    longer describe the actions taken), and the map is invertible, so the
    policy's distribution over actions is its latent distribution scaled
    (its entropy shifted by a constant). The observation is ignored.

    Examples:
        >>> import torch
        >>> m = AffineActionMap(latent_bound=2.0, low=torch.tensor([-1.0, 0.0]), high=torch.tensor([1.0, 4.0]))
        >>> m(None, torch.tensor([[-2.0, -2.0], [0.0, 0.0], [2.0, 1.0]]))
        tensor([[-1.,  0.],
                [ 0.,  2.],
                [ 1.,  3.]])
    """

    def __init__(self, latent_bound: float, low: torch.Tensor, high: torch.Tensor):
        super().__init__()
        if latent_bound <= 0:
            raise ValueError(f"latent_bound must be > 0, got {latent_bound}.")
        low, high = torch.as_tensor(low, dtype=torch.float32).reshape(-1), torch.as_tensor(high, dtype=torch.float32).reshape(-1)
        if low.shape != high.shape or not bool((high > low).all()):
            raise ValueError(f"the action box needs low < high elementwise, got low {low.tolist()} and high {high.tolist()}")
        self.latent_bound = float(latent_bound)
        self.latent_dim = self.action_dim = int(low.numel())
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, observation, latent: torch.Tensor, goal=None) -> torch.Tensor:
        frac = (latent + self.latent_bound) / (2 * self.latent_bound)
        return self.low + frac * (self.high - self.low)


class LatentActionTransform(Transform):
    """Lets a policy act in a CVAE's latent space; the decoder makes real actions.

    The policy writes ``latent_action`` (a box ``[-latent_bound,
    latent_bound]^latent_dim``); before every step of the base env the
    transform decodes it with the current observation (and goal) into
    ``action``. The decoded action stays in the rollout, so data collected
    through the transform holds both. Works on
    :class:`~torchrl_offhrl.envs.PessimisticModelEnv` and on a real
    environment (e.g. TorchRL's ``GymEnv``): the paper evaluates agents in the
    real env through the same decoder.

    Specs: ``action`` leaves the action spec for the state spec (it is an
    input of the base env that the policy does not write) and
    ``latent_action`` becomes the action.

    Args:
        decoder (CVAEDecoder): maps ``(observation, latent[, goal])`` to an
            action in the action box; any module with that signature and a
            ``latent_dim`` attribute works.
        latent_bound (float): half-width of the latent box (default 2.0,
            i.e. two standard deviations of the CVAE prior).
        clip (bool): clamp latent actions into the box before decoding
            (default ``True``); with ``False`` out-of-box latents are decoded
            as they are.
        latent_key / action_key / observation_key: tensordict keys.
        goal_key: key of the goal for goal-conditioned decoders.

    Examples:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
        >>> from torchrl_offhrl.envs import PessimisticModelEnv, LatentActionTransform
        >>> data = make_toy_dataset(num_episodes=10, episode_length=20)
        >>> ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(32,)).fit(data, max_epochs=2, progress=False)
        >>> cvae = ConditionalVAE.for_dataset(data, hidden_sizes=(32,)).fit(data, max_epochs=2, progress=False)
        >>> env = TransformedEnv(
        ...     PessimisticModelEnv(ens, data, batch_size=[8], seed=0),
        ...     LatentActionTransform(cvae.decoder),
        ... )
        >>> check_env_specs(env)
        >>> td = env.rollout(5, break_when_any_done=False)
        >>> td["latent_action"].shape, td["action"].shape
        (torch.Size([8, 5, 2]), torch.Size([8, 5, 2]))
    """

    def __init__(
        self,
        decoder: torch.nn.Module,
        latent_bound: float = DEFAULT_LATENT_BOUND,
        clip: bool = True,
        latent_key: str = "latent_action",
        action_key: str = "action",
        observation_key: str = "observation",
        goal_key: str | None = None,
    ):
        if latent_bound <= 0:
            raise ValueError(f"latent_bound must be > 0, got {latent_bound}.")
        super().__init__(in_keys_inv=[action_key], out_keys_inv=[latent_key])
        self.decoder = decoder  # decoded under no_grad; the caller's module is left as it is
        self.latent_dim = int(decoder.latent_dim)
        self.latent_bound = float(latent_bound)
        self.clip = clip
        self.latent_key = latent_key
        self.action_key = action_key
        self.observation_key = observation_key
        self.goal_key = goal_key
        self._warned = False

    def transform_input_spec(self, input_spec):
        action_spec = input_spec["full_action_spec", self.action_key]
        lead = action_spec.shape[:-1]
        bound = self.latent_bound
        latent_spec = Bounded(
            -bound, bound, (*lead, self.latent_dim), dtype=torch.float32, device=action_spec.device
        )
        input_spec["full_state_spec", self.action_key] = action_spec.clone()
        del input_spec["full_action_spec", self.action_key]
        input_spec["full_action_spec", self.latent_key] = latent_spec
        return input_spec

    def inv(self, tensordict: TensorDictBase) -> TensorDictBase:
        # No clone: the decoded action is written into the rollout's tensordict.
        return self._inv_call(tensordict)

    @torch.no_grad()
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        latent = tensordict.get(self.latent_key, None)
        if latent is None:
            raise KeyError(
                f"LatentActionTransform: the policy must write '{self.latent_key}' (found keys "
                f"{list(tensordict.keys())}); drop the transform to act with real actions."
            )
        if self.clip:
            latent = latent.clamp(-self.latent_bound, self.latent_bound)
        obs = tensordict.get(self.observation_key)
        goal = tensordict.get(self.goal_key) if self.goal_key is not None else None
        # The decoder runs where its weights live and the action comes back to the env's device: one decoder
        # (on a GPU, say) serves both the model env there and the real MuJoCo env on the CPU.
        dev = _module_device(self.decoder, obs.device)
        action = self.decoder(obs.to(dev), latent.to(device=dev, dtype=obs.dtype), None if goal is None else goal.to(dev)).to(obs.device)
        slot = tensordict.get(self.action_key, None)
        if (
            isinstance(slot, torch.Tensor)
            and not getattr(slot, "_offhrl_used", False)
            and slot.shape == action.shape
            and slot.dtype == action.dtype
        ):
            # Write into the unused slot left in the root tensordict (by this
            # transform at reset and after each step, or by TorchRL's reset
            # merge): inside a Compose, inverse transforms see a shallow
            # clone, and only an in-place write reaches the rollout's data.
            # Every tensor written is marked used, so no two steps ever share
            # the storage of their actions.
            slot.copy_(action)
            slot._offhrl_used = True
            return tensordict
        if slot is not None and self._in_compose() and not self._warned:
            self._warned = True
            warnings.warn(
                "LatentActionTransform inside a Compose got a tensordict whose 'action' slot was "
                "already used (a hand-written env.step / env.step_mdp loop): the decoded action "
                "reaches the base env but cannot be recorded in your tensordict. Use "
                "env.step_and_maybe_reset (as rollout and collectors do) or make the transform "
                "the env's own transform: TransformedEnv(base, LatentActionTransform(...)).",
                RuntimeWarning,
                stacklevel=2,
            )
        action._offhrl_used = True
        return tensordict.set(self.action_key, action)

    def _in_compose(self) -> bool:
        ref = self.__dict__.get("_container")
        return isinstance(ref() if ref is not None else None, Compose)

    def _action_slot(self, reference: TensorDictBase) -> torch.Tensor:
        # the parent is the env *before* this transform: "action" is its action
        spec = self.parent.full_action_spec.get(self.action_key, None) if self.parent is not None else None
        if spec is not None:
            slot = torch.zeros(spec.shape, dtype=spec.dtype, device=spec.device)
        else:
            obs = reference.get(self.observation_key)
            slot = torch.zeros(*obs.shape[:-1], self.decoder.action_dim, device=obs.device)
        return slot

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # a fresh slot for the first decoded action of the episode
        return tensordict_reset.set(self.action_key, self._action_slot(tensordict_reset))

    def _post_step_mdp_hooks(self, tensordict: TensorDictBase, tensordict_: TensorDictBase):
        # a fresh slot for the next step, so that no two steps share storage
        tensordict_.set(self.action_key, self._action_slot(tensordict_))
        return tensordict, tensordict_

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(latent_key={self.latent_key!r}, action_key={self.action_key!r}, "
            f"latent_dim={self.latent_dim}, latent_bound={self.latent_bound})"
        )


def _module_device(module: torch.nn.Module, default: torch.device) -> torch.device:
    """The device of ``module``'s first parameter or buffer (``default`` when it has none)."""
    for t in module.parameters():
        return t.device
    for t in module.buffers():
        return t.device
    return default
