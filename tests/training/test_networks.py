import pytest
import torch

from qnav.training.networks import QNetwork, StreamingQNetwork, conv_output_length


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


@pytest.mark.parametrize(("kind", "beams"), [("recurrent", 720), ("recurrent", None)])
def test_the_streaming_network_fed_a_window_from_any_state_gives_the_windows_q(
    kind: str, beams: int | None
) -> None:
    torch.manual_seed(0)
    network = QNetwork(kind, beams, hidden_size=32)  # type: ignore[arg-type]
    streaming = StreamingQNetwork(network, 5)
    frames = torch.rand(16, 5, network.frame_size)
    state = (torch.randn(16, 4, 32), torch.randn(16, 4, 32))
    for t in range(5):
        q, *state = streaming(frames[:, t], *state)
    torch.testing.assert_close(q, network(frames), rtol=1e-5, atol=1e-6)


def test_the_streaming_network_carries_every_window_in_progress() -> None:
    torch.manual_seed(0)
    network = QNetwork("recurrent", 720, hidden_size=32)
    streaming = StreamingQNetwork(network, 5)
    frames = torch.rand(4, 12, network.frame_size)
    state = (torch.zeros(4, 4, 32), torch.zeros(4, 4, 32))
    for t in range(12):
        q, *state = streaming(frames[:, t], *state)
        if t >= 4:
            torch.testing.assert_close(q, network(frames[:, t - 4 : t + 1]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("kind", "window"), [("feedforward", 5), ("recurrent", 1)])
def test_a_streaming_network_without_windows_in_progress_takes_no_state(
    kind: str, window: int
) -> None:
    network = QNetwork(kind, 720, hidden_size=32)  # type: ignore[arg-type]
    streaming = StreamingQNetwork(network, window)
    assert streaming.state_slots == 0
    frames = torch.rand(3, window, network.frame_size)
    (q,) = streaming(frames[:, -1])
    torch.testing.assert_close(q, network(frames), rtol=1e-5, atol=1e-6)


def test_the_streaming_network_has_the_networks_parameter_names() -> None:
    network = QNetwork("recurrent", 720, hidden_size=32)
    streaming = StreamingQNetwork(network, 5)
    assert list(streaming.state_dict()) == list(network.state_dict())


@pytest.mark.parametrize("kind", ["recurrent", "feedforward"])
def test_the_head_reads_the_window_summary(kind: str) -> None:
    network = QNetwork(kind, 720, 16)  # type: ignore[arg-type]
    frames = torch.rand(4, 5, network.frame_size)
    features = network.frame_features(frames)
    summary = network.window_summary(features)
    assert summary.shape == (4, network.summary_size)
    torch.testing.assert_close(network.head(summary), network(frames))
