import pytest
import torch

from training.networks import (
    QNetwork,
    StreamingQNetwork,
    centre_encoder,
    channel_activity,
    conv_output_length,
    near_scan_bins,
    scan_change,
)


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


def test_scan_change_is_zero_on_the_first_frame_in_metres_and_clipped() -> None:
    scans = torch.zeros(1, 3, 4)
    scans[0, 1] = torch.tensor([0.01, -0.01, 0.5, -0.5])  # ranges / 20 m
    change = scan_change(scans)
    assert torch.equal(change[0, 0], torch.zeros(4))
    torch.testing.assert_close(change[0, 1], torch.tensor([0.2, -0.2, 1.0, -1.0]))
    torch.testing.assert_close(change[0, 2], torch.tensor([-0.2, 0.2, -1.0, 1.0]))


def test_feedforward_with_scan_differences_sees_the_previous_frame_and_no_earlier() -> None:
    network = QNetwork("feedforward", 720, hidden_size=32, scan_difference=True)
    frames = torch.rand(2, 5, network.frame_size)
    earlier, previous = frames.clone(), frames.clone()
    earlier[:, :-2] = torch.rand_like(earlier[:, :-2])
    previous[:, -2] = torch.rand_like(previous[:, -2])
    torch.testing.assert_close(network(frames), network(earlier))
    assert not torch.allclose(network(frames), network(previous))


def test_a_finer_stride_keeps_more_positions() -> None:
    assert conv_output_length(720, stride=2) == 86
    network = QNetwork("recurrent", 720, hidden_size=32, conv_stride=2)
    assert network.encoder is not None and network.encoder.output_size == 8 * 86
    assert network(torch.rand(3, 5, network.frame_size)).shape == (3, 3)


def test_a_network_reading_scan_differences_is_not_streamed() -> None:
    network = QNetwork("recurrent", 720, hidden_size=32, scan_difference=True)
    with pytest.raises(ValueError, match="scan differences"):
        StreamingQNetwork(network, 5)


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


def test_a_centred_encoder_starts_every_channel_alive_on_about_half_of_the_scans() -> None:
    from sim.config import scenario
    from training.run import first_scans

    world = scenario("obstacles-inertia")
    torch.manual_seed(1)
    network = QNetwork("recurrent", 720, 64)
    assert network.encoder is not None
    probes = torch.from_numpy(first_scans(world, seed=7))
    default = channel_activity(network.encoder, probes)
    centre_encoder(network.encoder, torch.from_numpy(first_scans(world, seed=3)))
    centred = channel_activity(network.encoder, probes)  # other layouts than those centred on
    # torch's initialisation leaves channels that no scan switches on (dead from the start).
    assert any((layer == 0).any() for layer in default)
    for layer in centred:
        assert ((layer > 0.3) & (layer < 0.7)).all(), layer


def test_near_scan_bins_keep_each_sectors_nearest_return_as_a_share_of_the_near_range() -> None:
    scans = torch.ones(1, 12)
    scans[0, 1] = 0.1  # sector 0: 0.1 / 0.25
    scans[0, 5] = 0.05  # sector 1: 0.05 / 0.25
    scans[0, 6] = 0.3  # sector 2: beyond the near range
    bins = near_scan_bins(scans, 3, near_fraction=0.25)
    torch.testing.assert_close(bins, torch.tensor([[0.4, 0.2, 1.0]]))
    with pytest.raises(ValueError, match="12 beams do not split into 5"):
        near_scan_bins(scans, 5, near_fraction=0.25)


@pytest.mark.parametrize("kind", ["recurrent", "feedforward"])
def test_the_head_reads_the_window_summary(kind: str) -> None:
    network = QNetwork(kind, 720, 16)  # type: ignore[arg-type]
    frames = torch.rand(4, 5, network.frame_size)
    features = network.frame_features(frames)
    summary = network.window_summary(features)
    assert summary.shape == (4, network.summary_size)
    torch.testing.assert_close(network.head(summary), network(frames))
