"""Pictures in TensorBoard: the folded grid, the binning of held-out errors, the rendering, and
the callback writing images and hyperparameters into the event file."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from cme_agent import CMEPolicyIteration
from cme_agent.config import ObservationConfig
from cme_agent.encoding import ObservationEncoder
from cme_agent.heatmaps import EMPTY, LEFT, VIRIDIS, Axis, colorize, heatmap
from cme_agent.pictures import (
    PICTURE_TAGS,
    PictureCallback,
    agent_hparams,
    agent_pictures,
    bin_mean,
    cell_centres,
    choose_dims,
    fold,
    folded_dims,
    grid_observations,
)
from tests.conftest import small_kwargs


def pendulum_encoder() -> ObservationEncoder:
    space = spaces.Box(np.array([-1, -1, -8], np.float32), np.array([1, 1, 8], np.float32))
    return ObservationEncoder(space, ObservationConfig(angle_pairs=((0, 1),)))


def test_angle_pair_folds_to_one_coordinate():
    dims = folded_dims(pendulum_encoder())
    assert [dim.indices for dim in dims] == [(0, 1), (2,)]
    assert (dims[0].low, dims[0].high) == (-math.pi, math.pi)
    assert (dims[1].low, dims[1].high) == (-8.0, 8.0)
    assert choose_dims(dims, [1, 2]) == choose_dims(dims, [0, 2]) == [0, 1]
    assert choose_dims(dims, [2, 0]) == [1, 0]
    with pytest.raises(ValueError, match="two different coordinates"):
        choose_dims(dims, [0, 1])  # the same angle twice
    with pytest.raises(ValueError, match="dim 5"):
        choose_dims(dims, [5])


def test_grid_observations_x_fastest_and_on_the_circle():
    encoder = pendulum_encoder()
    dims = folded_dims(encoder)
    obs = grid_observations(encoder, dims, [0, 1], resolution=4)
    assert obs.shape == (16, 3)
    torch.testing.assert_close(obs[:, 0] ** 2 + obs[:, 1] ** 2, torch.ones(16))
    folded = fold(obs, dims).reshape(4, 4, 2)  # [y, x, coordinate]
    np.testing.assert_allclose(folded[0, :, 0], cell_centres(dims[0], 4), atol=1e-6)  # x varies along a row
    np.testing.assert_allclose(folded[:, 0, 1], cell_centres(dims[1], 4), atol=1e-6)  # y along a column, lowest first


def test_slice_holds_the_other_coordinates():
    space = spaces.Box(-np.ones(4, np.float32), np.array([1, 2, 3, 4], np.float32))
    encoder = ObservationEncoder(space, ObservationConfig())
    dims = folded_dims(encoder)
    obs = grid_observations(encoder, dims, choose_dims(dims, [3, 1]), resolution=5, fixed={2: 0.25})
    assert obs.shape == (25, 4)
    assert torch.all(obs[:, 0] == 0.0)  # the box centre
    assert torch.all(obs[:, 2] == 0.25)  # the given value
    assert obs[:, 3].unique().numel() == obs[:, 1].unique().numel() == 5


def test_bin_mean_averages_per_cell_and_leaves_empty_cells_blank():
    dims = folded_dims(pendulum_encoder())[1:]  # velocity in [-8, 8]
    coordinates = np.array([[-7.9], [-7.0], [7.9], [9.0]])  # two in the first cell, one in the last, one outside
    mean = bin_mean(coordinates, np.array([1.0, 3.0, 5.0, 100.0]), dims, resolution=4)
    assert mean[0] == 2.0 and mean[3] == 5.0
    assert np.isnan(mean[1]) and np.isnan(mean[2])
    two = bin_mean(np.array([[math.pi - 0.1, -7.9]]), np.array([4.0]), folded_dims(pendulum_encoder()), resolution=2)
    assert two[0, 1] == 4.0 and np.isnan(two).sum() == 3  # [y, x]: lowest velocity, highest angle


def test_heatmap_orientation_and_blank_cells():
    values = np.array([[0.0, np.nan], [1.0, 1.0]])  # row 0 is the lowest y
    image = heatmap(values, Axis("x", 0, 1), Axis("y", 0, 1), ["title"])
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    column = image[:, LEFT + 10]
    rows = np.flatnonzero((column == colorize(np.array(1.0), 0, 1)).all(axis=1))
    low_rows = np.flatnonzero((column == colorize(np.array(0.0), 0, 1)).all(axis=1))
    assert rows.size and low_rows.size and rows.max() < low_rows.min()  # the high values are drawn on top
    np.testing.assert_array_equal(colorize(np.array([np.nan]), 0, 1)[0], EMPTY)
    np.testing.assert_array_equal(colorize(np.array([5.0]), 0, 1)[0], VIRIDIS[-1].astype(np.uint8))


def test_pictures_of_a_discrete_one_dim_agent_draw_no_random_number():
    env = gym.make("ToyChain-v0", discrete_actions=True)
    kwargs = {key: value for key, value in small_kwargs().items() if key != "policy_kwargs"}
    model = CMEPolicyIteration("CMEPolicy", env, seed=0, **kwargs)
    model.learn(300)
    rngs = (model._torch_rng.get_state(), model._np_rng.bit_generator.state)
    pictures = agent_pictures(model, resolution=16)
    assert set(pictures) == set(PICTURE_TAGS)
    assert all(picture.dtype == np.uint8 and picture.shape[2] == 3 for picture in pictures.values())
    assert torch.equal(model._torch_rng.get_state(), rngs[0]) and model._np_rng.bit_generator.state == rngs[1]


class UnboundedVelocity(gym.ObservationWrapper):
    """Pendulum with an infinite velocity bound: the box of that dim is estimated from data."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        high = np.array([1, 1, np.inf], np.float32)
        self.observation_space = spaces.Box(-high, high)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return observation


def test_nothing_drawn_before_the_box_is_known():
    model = CMEPolicyIteration("CMEPolicy", UnboundedVelocity(gym.make("Pendulum-v1")), seed=0, **small_kwargs())
    assert model.dynamics.obs_encoder.needs_fit
    assert agent_pictures(model) == {}
    model.learn(200)  # the random phase (100 steps) fits the box
    assert not model.dynamics.obs_encoder.needs_fit
    assert set(agent_pictures(model, resolution=8)) == set(PICTURE_TAGS)


def test_images_and_hparams_in_the_event_file(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    model = CMEPolicyIteration("CMEPolicy", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **small_kwargs())
    model.learn(300, callback=PictureCallback(every=2, resolution=16), tb_log_name="run")
    events = EventAccumulator(str(next(tmp_path.glob("run_*")))).Reload()
    assert set(PICTURE_TAGS) <= set(events.Tags()["images"])
    # iteration 2 at the start of iteration 3, and the last iteration (3) at the end of training
    assert [event.step for event in events.Images("pictures/value")] == [200, 300]
    assert events.Images("pictures/value")[0].width > 256
    content = events.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    logged = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
    assert logged["gamma"].number_value == pytest.approx(model.gamma)
    assert logged["env_id"].string_value == "Pendulum-v1"
    assert logged["feature_selection.max_features"].number_value == 20
    assert set(agent_hparams(model)) <= set(logged)


def test_callback_settings_are_checked():
    with pytest.raises(ValueError, match="every=0"):
        PictureCallback(every=0)
    callback = PictureCallback(picture_dims=("2", 0), fixed={"3": "0.5"})  # as Hydra may pass them
    assert callback.picture_dims == [2, 0] and callback.fixed == {3: 0.5}
