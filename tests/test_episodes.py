"""EpisodeAssembler and cut_episodes on hand-built collector-like batches whose episodes span batches."""

import io

import pytest
import torch
from tensordict import TensorDict

from torchrl_silp.data.episodes import EpisodeAssembler, cut_episodes

# per env, the lengths of its successive episodes; the last one of each env is left unfinished
LENGTHS = [[3, 7, 2, 9], [5, 1, 1, 4, 8], [11, 6]]
T = 4  # steps per env per batch


def collector_stream(lengths=LENGTHS, steps=T, n_batches=5):
    """Batches ``[envs, steps]`` as a collector writes them, and the ground truth.

    Trajectory ids are handed out as episodes start (envs in order at each time step), as
    TorchRL's collector does; every step records its episode's id and its time in the episode.
    """
    n_envs = len(lengths)
    next_id = 0
    current = [None] * n_envs  # (traj id, length, t)
    episode_index = [0] * n_envs
    ids, ts, dones, lens = (torch.zeros(n_envs, steps * n_batches, dtype=torch.long) for _ in range(4))
    truth = {}  # traj id -> (length, finished)
    for step in range(steps * n_batches):
        for e in range(n_envs):
            if current[e] is None:
                length = lengths[e][min(episode_index[e], len(lengths[e]) - 1)]
                if episode_index[e] >= len(lengths[e]) - 1:
                    length = 10**6  # the last episode never finishes
                episode_index[e] += 1
                current[e] = (next_id, length, 0)
                truth[next_id] = length
                next_id += 1
            traj, length, t = current[e]
            ids[e, step], ts[e, step], lens[e, step] = traj, t, min(length, 10**6)
            dones[e, step] = t == length - 1
            current[e] = None if t == length - 1 else (traj, length, t + 1)
    batches = []
    for b in range(n_batches):
        s = slice(b * steps, (b + 1) * steps)
        batches.append(
            TensorDict(
                {
                    ("collector", "traj_ids"): ids[:, s].clone(),
                    "t": ts[:, s].clone(),
                    "observation": torch.stack([ids[:, s], ts[:, s]], -1).float(),
                    ("next", "done"): dones[:, s].clone().bool().unsqueeze(-1),
                    ("next", "truncated"): torch.zeros(n_envs, steps, 1, dtype=torch.bool),
                },
                batch_size=[n_envs, steps],
            )
        )
    finished_at = {}  # traj id -> batch index where its last step is
    for b, batch in enumerate(batches):
        done = batch["next", "done"].squeeze(-1)
        for traj in batch["collector", "traj_ids"][done].tolist():
            finished_at[traj] = b
    return batches, truth, finished_at


def split(out):
    """A flat output -> {traj id: tensor of its t's, in the order they appear}, checking contiguity."""
    ids = out["collector", "traj_ids"]
    episodes, order = {}, []
    for i, traj in enumerate(ids.tolist()):
        if not order or order[-1] != traj:
            assert traj not in episodes, "an episode's steps are not contiguous"
            order.append(traj)
            episodes[traj] = []
        episodes[traj].append(int(out["t"][i]))
    assert order == sorted(order)
    return episodes


def test_episodes_returned_whole_in_time_order_when_they_finish():
    batches, truth, finished_at = collector_stream()
    assert max(truth[t] for t in finished_at) > T  # some episodes span 2 or more batches
    asm = EpisodeAssembler()
    seen = {}
    for b, batch in enumerate(batches):
        original = batch.clone()
        out = asm.push(batch)
        assert (batch == original).all()  # the input is left alone
        expected = sorted(t for t, at in finished_at.items() if at == b)
        if not expected:
            assert out is None
            continue
        assert out.batch_size == (sum(truth[t] for t in expected),)
        episodes = split(out)
        assert sorted(episodes) == expected
        for traj, steps in episodes.items():
            assert steps == list(range(truth[traj]))  # whole, in time order
            assert traj not in seen
            seen[traj] = b
        done = out["next", "done"].squeeze(-1)
        last = torch.ones_like(done)
        last[:-1] = out["collector", "traj_ids"][1:] != out["collector", "traj_ids"][:-1]
        assert torch.equal(done, last)  # each returned episode ends at its done step, and only there
        # the pending pieces are exactly the steps of the unfinished episodes so far
        n_steps = (b + 1) * T * len(LENGTHS)
        assert asm.num_pending == n_steps - sum(truth[t] for t in seen)
    assert seen == finished_at
    pending_ids = set(asm.pending["collector", "traj_ids"].tolist())
    assert pending_ids == set(truth) - set(finished_at) and len(pending_ids) == len(LENGTHS)
    leftover = asm.flush()
    assert asm.flush() is None and asm.pending is None and asm.num_pending == 0
    # flushed pieces keep each episode's steps in time order
    for traj in pending_ids:
        t = leftover["t"][leftover["collector", "traj_ids"] == traj]
        assert t.tolist() == list(range(t.numel()))


def test_state_dict_round_trip_mid_stream():
    batches, _, _ = collector_stream()
    asm = EpisodeAssembler()
    for batch in batches[:2]:
        asm.push(batch)
    assert asm.num_pending > 0
    buffer = io.BytesIO()
    torch.save(asm.state_dict(), buffer)
    buffer.seek(0)
    restored = EpisodeAssembler()
    restored.load_state_dict(torch.load(buffer, weights_only=True))
    assert restored.num_pending == asm.num_pending
    assert (restored.pending == asm.pending).all()
    for batch in batches[2:]:
        a, b = asm.push(batch), restored.push(batch)
        assert (a is None) == (b is None)
        if a is not None:
            assert (a == b).all()
    assert (asm.flush() == restored.flush()).all()
    # nothing pending: a None state, which restores to nothing pending
    assert asm.state_dict() == {"pending": None}
    restored.load_state_dict({"pending": None})
    assert restored.flush() is None
    # a TensorDict of pending pieces (the recipes' former checkpoint format) loads too
    restored.load_state_dict({"pending": batches[0]})
    assert restored.num_pending == batches[0].numel()
    with pytest.raises(KeyError):
        restored.load_state_dict({})


def test_cut_episodes_makes_flushed_pieces_whole_truncated_episodes():
    batches, truth, finished_at = collector_stream()
    asm = EpisodeAssembler()
    for batch in batches[:3]:
        asm.push(batch)
    pieces = asm.flush()
    original = pieces.clone()
    out = cut_episodes(pieces)
    assert (pieces == original).all()
    episodes = split(out)
    for traj, steps in episodes.items():
        assert steps == list(range(len(steps)))
        assert traj not in finished_at or finished_at[traj] >= 3
    ids = out["collector", "traj_ids"]
    last = torch.ones_like(ids, dtype=torch.bool)
    last[:-1] = ids[1:] != ids[:-1]
    assert torch.equal(out["next", "done"].squeeze(-1), last)
    assert torch.equal(out["next", "truncated"].squeeze(-1), last)
    # flags already set stay set (the cut only adds)
    pieces["next", "done"][:] = True
    assert cut_episodes(pieces)["next", "done"].all()


def test_on_a_real_collector():
    """The layout the assembler assumes is the one TorchRL's collector writes."""
    from torchrl.collectors import Collector
    from torchrl.envs.utils import RandomPolicy

    from torchrl_silp import UR5eReachEnv

    torch.manual_seed(0)
    env = UR5eReachEnv(num_envs=3, seed=0, max_steps=5)
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=12, total_frames=48)
    asm = EpisodeAssembler()
    n_out = 0
    for batch in collector:
        out = asm.push(batch)
        if out is None:
            continue
        ids = out["collector", "traj_ids"]
        for traj in ids.unique().tolist():
            ep = out[ids == traj]
            steps = ep["step_count"].squeeze(-1)
            assert steps.tolist() == list(range(ep.numel()))  # whole, from its first step, in order
            assert ep["next", "done"].squeeze(-1).tolist() == [False] * (ep.numel() - 1) + [True]
            torch.testing.assert_close(ep["next", "joint_position"][:-1], ep["joint_position"][1:])
        n_out += out.numel()
    collector.shutdown()
    assert n_out > 0 and n_out + asm.num_pending == 48
