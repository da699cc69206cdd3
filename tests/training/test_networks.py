import pytest
import torch

from training.networks import QNetwork, conv_output_length


def test_paper_encoder_turns_720_beams_into_25_positions_of_8_channels() -> None:
    assert conv_output_length(720) == 25
    network = QNetwork("recurrent", 720)
    assert network.encoder is not None and network.encoder.output_size == 200


@pytest.mark.parametrize("kind", ["recurrent", "feedforward"])
@pytest.mark.parametrize("beams", [720, None])
def test_every_variant_maps_a_window_to_three_q_values(kind: str, beams: int | None) -> None:
    network = QNetwork(kind, beams, hidden_size=32)  # type: ignore[arg-type]
    frames = torch.rand(4, 5, network.frame_size)
    assert network(frames).shape == (4, 3)


def test_lidarless_network_has_no_convolutions() -> None:
    network = QNetwork("recurrent", None)
    assert network.encoder is None
    assert not any(isinstance(m, torch.nn.Conv1d) for m in network.modules())


def test_recurrence_matches_torch_lstm_from_a_zero_state() -> None:
    torch.manual_seed(0)
    network = QNetwork("recurrent", 720)
    frames = torch.rand(8, 5, network.frame_size)
    features = network.frame_features(frames)
    assert network.lstm is not None
    output, _ = network.lstm(features)
    expected = network.head(output[:, -1])
    torch.testing.assert_close(network(frames), expected, rtol=1e-5, atol=1e-6)


def test_feedforward_reads_only_the_last_frame() -> None:
    network = QNetwork("feedforward", 720, hidden_size=32)
    frames = torch.rand(2, 5, network.frame_size)
    changed = frames.clone()
    changed[:, :-1] = torch.rand_like(changed[:, :-1])
    torch.testing.assert_close(network(frames), network(changed))


def test_recurrent_q_depends_on_earlier_frames() -> None:
    network = QNetwork("recurrent", 720, hidden_size=32)
    frames = torch.rand(2, 5, network.frame_size)
    changed = frames.clone()
    changed[:, 0] = torch.rand_like(changed[:, 0])
    assert not torch.allclose(network(frames), network(changed))
