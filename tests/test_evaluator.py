"""The T2M evaluator: shapes, the released checkpoint layout, model directories, words,
training through `segmo fit`, and the action classifier on a tiny built-in corpus."""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from segmo.models.evaluator import EvaluatorConfig, T2MEvaluator
from segmo.models.pretrained import load_pretrained
from segmo.text.vocabulary import (
    POS_INDEX,
    Vocabulary,
    parse_tokens,
    pos_category,
    read_text_tokens,
    tag_caption,
)

REPO = Path(__file__).resolve().parents[1]
SMALL = dict(word_dim=12, text_hidden=8, movement_hidden=10, movement_dim=6, motion_hidden=8, embed_dim=5)
WORDS = ["sos", "eos", "unk", "a", "person", "walks", "forward", "waves", "left", "hand"]


def small_evaluator(seed: int = 0, **overrides) -> T2MEvaluator:
    torch.manual_seed(seed)
    model = T2MEvaluator(EvaluatorConfig(num_words=len(WORDS), **{**SMALL, **overrides}))
    model.set_vocabulary(Vocabulary(WORDS))
    return model.eval()


def test_forward_shapes_and_lengths() -> None:
    model = small_evaluator()
    words, pos, lengths = model.vocabulary.batch([tag_caption("a person walks forward."), tag_caption("waves")])
    assert words.shape == pos.shape == (2, 6) and lengths.tolist() == [6, 3]
    motion = torch.randn(2, 40, 263)
    out = model(words, pos, lengths, motion, torch.tensor([40, 24]))
    assert out.text.shape == (2, 5) and out.motion.shape == (2, 5)
    # Frames past a motion's length (beyond the conv overlap) do not change its embedding.
    changed = motion.clone()
    changed[1, 32:] = 100.0
    np.testing.assert_allclose(model.encode_motion(changed, torch.tensor([40, 24]))[1].detach(),
                               out.motion[1].detach(), atol=1e-5)
    with pytest.raises(ValueError, match="features"):
        model.encode_motion(torch.randn(1, 8, 251), torch.tensor([8]))


def test_embed_motion_renormalises_with_its_own_statistics() -> None:
    model = small_evaluator()
    g = torch.Generator().manual_seed(0)
    model.set_statistics(torch.randn(263, generator=g), torch.rand(263, generator=g) + 0.5)
    raw = torch.randn(3, 16, 263, generator=g)
    ds_mean, ds_std = torch.randn(263, generator=g), torch.rand(263, generator=g) + 0.1
    z = (raw - ds_mean) / ds_std
    expected = model.encode_motion((raw - model.mean) / model.std, torch.tensor([16, 12, 8]))
    got = model.embed_motion(z, torch.tensor([16, 12, 8]), mean=ds_mean, std=ds_std)
    np.testing.assert_allclose(got, expected.detach(), atol=1e-4)
    np.testing.assert_allclose(model.embed_motion(raw, torch.tensor([16, 12, 8])), expected.detach(), atol=1e-5)


def test_words_and_pos() -> None:
    assert parse_tokens("a/DET man/NOUN waves/VERB") == [("a", "DET"), ("man", "NOUN"), ("waves", "VERB")]
    assert pos_category("left", "ADJ") == POS_INDEX["Loc_VIP"]  # VIP list overrides the tagger
    assert pos_category("and", "CCONJ") == POS_INDEX["OTHER"]  # not one of the 15 categories
    assert [p for _, p in tag_caption("A man walks slowly, then sits.")] == ["DET", "NOUN", "VERB", "ADV", "ADV", "VERB"]
    vocab = Vocabulary(WORDS)
    words, pos = vocab.encode([("a", "DET"), ("zebra", "NOUN"), ("hand", "NOUN")])
    assert words == [0, 3, 2, 9, 1]  # sos a unk hand eos
    assert pos == [POS_INDEX[p] for p in ("OTHER", "DET", "OTHER", "Body_VIP", "OTHER")]
    assert len(vocab.encode([("a", "DET")] * 30)[0]) == 22  # 20 words + sos + eos


def test_contrastive_losses_prefer_matched_pairs() -> None:
    from segmo.tasks.evaluator import EvaluatorTask, infonce_loss, margin_contrastive_loss

    g = torch.Generator().manual_seed(0)
    motion = 5 * torch.randn(8, 4, generator=g)
    close, far = motion + 0.01, motion[torch.arange(8).roll(1)]
    batch = {"caption": [f"c{i}" for i in range(7)] + ["c0"], "id": [str(i) for i in range(8)]}
    negative = EvaluatorTask.negatives(batch)
    assert not negative[0, 7] and not negative[3, 3] and negative[0, 1]  # same caption, same motion
    for loss in (lambda t: infonce_loss(t, motion, negative, 1.0), lambda t: margin_contrastive_loss(t, motion, negative, 10.0)):
        assert float(loss(close)["loss"]) < float(loss(far)["loss"])


def _write_official(model: T2MEvaluator, root: Path) -> tuple[Path, Path]:
    """The released layout: text_mot_match/model/finest.tar, text_mot_match/meta/*.npy, GloVe files
    (words stored in a shuffled row order to exercise the index file)."""
    ckpt_dir = root / "t2m" / "text_mot_match" / "model"
    ckpt_dir.mkdir(parents=True)
    (root / "t2m" / "text_mot_match" / "meta").mkdir()
    np.save(root / "t2m" / "text_mot_match" / "meta" / "mean.npy", model.mean.numpy())
    np.save(root / "t2m" / "text_mot_match" / "meta" / "std.npy", model.std.numpy())
    torch.save({"movement_encoder": model.movement_encoder.state_dict(),
                "text_encoder": model.text_encoder.state_dict(),
                "motion_encoder": model.motion_encoder.state_dict(), "epoch": 7},
               ckpt_dir / "finest.tar")
    glove = root / "glove"
    glove.mkdir()
    rows = np.random.default_rng(0).permutation(len(WORDS))
    vectors = np.zeros((len(WORDS), model.config.word_dim), np.float32)
    vectors[rows] = model.word_embedding.weight.detach().numpy()
    np.save(glove / "our_vab_data.npy", vectors)
    with open(glove / "our_vab_words.pkl", "wb") as f:
        pickle.dump(list(reversed(WORDS)), f)
    with open(glove / "our_vab_idx.pkl", "wb") as f:
        pickle.dump({w: int(r) for w, r in zip(WORDS, rows, strict=True)}, f)
    return ckpt_dir / "finest.tar", glove


def test_official_checkpoint_layout_loads(tmp_path: Path) -> None:
    source = small_evaluator(seed=1)
    source.set_statistics(torch.randn(263), torch.rand(263) + 0.5)
    # The released module/parameter names.
    assert set(source.movement_encoder.state_dict()) == {
        "main.0.weight", "main.0.bias", "main.3.weight", "main.3.bias", "out_net.weight", "out_net.bias"}
    gru = {f"gru.{k}_{s}l0{r}" for k in ("weight", "bias") for s in ("ih_", "hh_") for r in ("", "_reverse")}
    head = {f"output_net.{i}.{k}" for i in (0, 1, 3) for k in ("weight", "bias")}
    assert set(source.text_encoder.state_dict()) == {
        "hidden", "pos_emb.weight", "pos_emb.bias", "input_emb.weight", "input_emb.bias"} | gru | head
    assert set(source.motion_encoder.state_dict()) == {"hidden", "input_emb.weight", "input_emb.bias"} | gru | head

    checkpoint, glove = _write_official(source, tmp_path)
    loaded = T2MEvaluator.from_official(checkpoint, glove)
    assert loaded.config.feature_dim == 263 and loaded.config.motion_hidden == SMALL["motion_hidden"]
    assert sorted(loaded.vocabulary.words) == sorted(WORDS) and not loaded.word_embedding.weight.requires_grad
    captions = ["a person walks forward.", [("waves", "VERB"), ("left", "ADJ"), ("hand", "NOUN")]]
    np.testing.assert_allclose(loaded.embed_captions(captions), source.embed_captions(captions), atol=1e-6)
    z = torch.randn(2, 32, 263)
    lengths = torch.tensor([32, 20])
    mean, std = torch.zeros(263), torch.ones(263)
    np.testing.assert_allclose(loaded.embed_motion(z, lengths, mean, std), source.embed_motion(z, lengths, mean, std),
                               atol=1e-5)
    with pytest.raises(FileNotFoundError, match="statistics"):
        T2MEvaluator.from_official(checkpoint, glove, mean=tmp_path / "nope.npy")


def test_save_load_round_trip(tmp_path: Path) -> None:
    model = small_evaluator(seed=2)
    model.set_statistics(torch.randn(263), torch.rand(263) + 0.5)
    model.save_pretrained(tmp_path / "ev", meta={"skeleton": "t2m"})
    loaded = load_pretrained(tmp_path / "ev")
    assert isinstance(loaded, T2MEvaluator) and loaded.vocabulary.words == WORDS
    torch.testing.assert_close(loaded.mean, model.mean)
    captions = ["a person waves the left hand"]
    np.testing.assert_allclose(loaded.embed_captions(captions), model.embed_captions(captions), atol=1e-6)
    z = torch.randn(1, 24, 263)
    np.testing.assert_allclose(loaded.embed_motion(z, torch.tensor([24])), model.embed_motion(z, torch.tensor([24])),
                               atol=1e-6)


# ---------------------------------------------------------------- with the built-in corpus

HAVE_SYNTH = importlib.util.find_spec("segmo.synth") is not None


@pytest.fixture(scope="module")
def tiny_corpus(tmp_path_factory) -> Path:
    if not HAVE_SYNTH:
        pytest.skip("segmo.synth is not in this checkout yet")
    from segmo.synth.corpus import build_corpus

    return build_corpus(tmp_path_factory.mktemp("corpus") / "synth", 16, seed=0, progress=False)


def test_text_tokens_of_the_corpus(tiny_corpus: Path) -> None:
    tokens = read_text_tokens(next((tiny_corpus / "texts").glob("*.txt")))
    assert tokens and all(isinstance(w, str) and isinstance(p, str) for line in tokens for w, p in line)


def test_caption_tokens(tiny_corpus: Path) -> None:
    from segmo.text.vocabulary import CaptionTokens

    tokens = CaptionTokens(tiny_corpus)
    mid = (tiny_corpus / "train.txt").read_text().split()[0]
    line = (tiny_corpus / "texts" / f"{mid}.txt").read_text().splitlines()[1]
    assert tokens("ignored", mid, 1) == parse_tokens(line.split("#")[1])
    assert tokens("A man waves.", "missing-id", 0) == tag_caption("A man waves.")


@pytest.mark.slow
def test_fit_synthetic_config(tiny_corpus: Path, tmp_path: Path) -> None:
    from segmo.export import export
    from segmo.training.cli import main as cli_main

    small = {k: 8 for k in ("word_dim", "text_hidden", "movement_hidden", "movement_dim", "motion_hidden")}
    argv = ["fit", "--config", str(REPO / "configs/evaluator/synthetic.yaml"), f"--data.root={tiny_corpus}",
            f"--runs_dir={tmp_path / 'runs'}", "--trainer.max_epochs=1", "--trainer.check_val_every_n_epoch=1",
            "--trainer.enable_progress_bar=false", "--data.init_args.batch_size=8",
            *[f"--model.init_args.{k}={v}" for k, v in small.items()], "--model.init_args.embed_dim=4"]
    cli = cli_main(argv)
    assert cli.trainer.global_step > 0 and "val/loss" in cli.trainer.callback_metrics
    model = cli.model.export_model()
    assert model.vocabulary.words[:3] == ["sos", "eos", "unk"] and len(model.vocabulary) > 10
    torch.testing.assert_close(model.mean, cli.datamodule.mean)
    ckpt = next((tmp_path / "runs" / "evaluator" / "synthetic").glob("version_*/checkpoints/last.ckpt"))
    out = export(ckpt, tmp_path / "exported")
    loaded = load_pretrained(out)
    assert isinstance(loaded, T2MEvaluator) and loaded.vocabulary.words == model.vocabulary.words
    np.testing.assert_allclose(loaded.embed_captions(["a person walks"]), model.eval().embed_captions(["a person walks"]),
                               atol=1e-6)


@pytest.mark.slow
def test_fit_action_classifier_config(tiny_corpus: Path, tmp_path: Path) -> None:
    """configs/action_classifier/synthetic.yaml through `segmo fit` and `segmo export`."""
    from segmo.data.layout import read_motion, read_split
    from segmo.export import export
    from segmo.models.action_classifier import ActionClassifier
    from segmo.training.cli import main as cli_main

    argv = ["fit", "--config", str(REPO / "configs/action_classifier/synthetic.yaml"),
            f"--data.root={tiny_corpus}", f"--runs_dir={tmp_path / 'runs'}", "--trainer.max_epochs=2",
            "--trainer.enable_progress_bar=false", "--data.init_args.batch_size=8",
            "--model.init_args.width=8", "--model.init_args.depth=2"]
    cli = cli_main(argv)
    assert cli.trainer.global_step > 0 and "val/frame_accuracy" in cli.trainer.callback_metrics
    ckpt = next((tmp_path / "runs" / "action_classifier" / "synthetic").glob("version_*/checkpoints/last.ckpt"))
    loaded = load_pretrained(export(ckpt, tmp_path / "exported"))
    model = cli.model.export_model().eval()
    assert isinstance(loaded, ActionClassifier) and loaded.classes == cli.datamodule.classes
    torch.testing.assert_close(loaded.mean, cli.datamodule.mean)
    x = read_motion(tiny_corpus, read_split(tiny_corpus, "val")[0])
    np.testing.assert_allclose(loaded.frame_probabilities(x), model.frame_probabilities(x), atol=1e-6)


@pytest.mark.slow
def test_fit_attribute_classifier_config(tiny_corpus: Path, tmp_path: Path) -> None:
    """configs/attribute_classifier/synthetic.yaml through `segmo fit` and `segmo export`;
    the exported model reads a span's attributes the same as the trained one."""
    from segmo.data.attributes import ATTRIBUTES
    from segmo.data.layout import read_motion, read_split
    from segmo.export import export
    from segmo.models.action_classifier import AttributeClassifier
    from segmo.training.cli import main as cli_main

    cli = cli_main(["fit", "--config", str(REPO / "configs/attribute_classifier/synthetic.yaml"),
                    f"--data.root={tiny_corpus}", f"--runs_dir={tmp_path / 'runs'}",
                    "--trainer.max_epochs=2", "--trainer.enable_progress_bar=false",
                    "--data.init_args.batch_size=8", "--model.init_args.width=8",
                    "--model.init_args.depth=2"])
    assert cli.trainer.global_step > 0 and "val/loss" in cli.trainer.callback_metrics
    ckpt = next((tmp_path / "runs" / "attribute_classifier" / "synthetic").glob("version_*/checkpoints/last.ckpt"))
    loaded = load_pretrained(export(ckpt, tmp_path / "exported"))
    assert isinstance(loaded, AttributeClassifier) and len(loaded.classes) == 11
    x = read_motion(tiny_corpus, read_split(tiny_corpus, "val")[0])
    found = loaded.span_attributes(x, 0, 20)
    assert found == cli.model.export_model().span_attributes(x, 0, 20)
    assert all(found[name] in values for name, values in ATTRIBUTES.items())


def test_action_classifier_fit_predict_save(tiny_corpus: Path, tmp_path: Path) -> None:
    from segmo.data.layout import read_actions as read_ground_truth
    from segmo.evaluation.action_order import evaluate_action_order
    from segmo.models.action_classifier import ActionClassifier
    from segmo.tasks.action_classifier import train_action_classifier

    clf = train_action_classifier(tiny_corpus, epochs=25, width=32, depth=3, lr=5e-3)
    train = (tiny_corpus / "train.txt").read_text().split()
    result = evaluate_action_order(clf, tiny_corpus, split="train")
    assert result["frame_accuracy"] > 0.6  # memorises its tiny training set
    seq = clf.predict_sequence(np.load(tiny_corpus / "new_joint_vecs" / f"{train[0]}.npy"))
    assert seq and set(seq) <= set(clf.classes)
    assert set(read_ground_truth(tiny_corpus, train[0])[0]) <= set(clf.classes)
    clf.save_pretrained(tmp_path / "clf")
    loaded = ActionClassifier.from_pretrained(tmp_path / "clf")
    x = np.load(tiny_corpus / "new_joint_vecs" / f"{train[1]}.npy")
    np.testing.assert_allclose(loaded.frame_probabilities(x), clf.frame_probabilities(x), atol=1e-6)
    assert loaded.predict_sequence(x) == clf.predict_sequence(x)
