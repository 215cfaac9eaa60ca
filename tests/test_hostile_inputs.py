"""Hostile inputs to every command and to the notebook API: one clear line, nothing lost.

Each CLI case runs ``segmo ARGV`` in-process and asserts exit status 2, no traceback, and
a last line that names the file (and line) or the argument that is wrong. Each API case
asserts the exception type and that its message names what is wrong. The cases are the
table in docs/hostile-inputs.md; a test keeps the two in step.

Placeholders in a CLI case's argv are filled from the `world` fixture: {bundle} (a tiny
random SegMo bundle), {corpus} (a tiny built-in corpus), {tmp} (a scratch folder), {empty}
(an empty argument) and the corrupt files `_corrupt_files` writes there. A case runs in
`world["cwd"]`, a folder holding a file of the user's that must survive it.

Regenerate the table with the messages of this run:
    SEGMO_HOSTILE_TABLE=docs/hostile-inputs.md python -m pytest tests/test_hostile_inputs.py
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import cli_failure, hash_encoder
from test_pipeline import TEXT_DIM, build_stages

from segmo.errors import SegmoError
from segmo.pipeline import SegMo

REPO = Path(__file__).resolve().parents[1]
TABLE = REPO / "docs" / "hostile-inputs.md"
MESSAGES: dict[str, str] = {}  # case id -> the line it printed (or the exception), this run


@dataclass(frozen=True)
class Cli:
    """`segmo ARGV` must fail with one line containing `names`."""

    id: str
    argv: str  # split on spaces after the placeholders are filled
    names: str
    what: str  # the hostile input, for the table

    @property
    def command(self) -> str:
        return self.argv.split()[0]


GEN = "generate --model {bundle} --out {tmp}/gen"
GROUND = "ground --model {bundle} --text a-person-walks"
CLI_CASES = [
    # -- segmo (the dispatcher)
    Cli("unknown-command", "generat --model {bundle}", "unknown command 'generat'",
        "a misspelt command"),
    # -- segmo generate
    Cli("generate-empty-text", GEN + " --text", "text 0", "an empty prompt (`--text \"\"`)"),
    Cli("generate-wordless-text", GEN + " --text ...", "text 0", "a prompt without words"),
    Cli("generate-guidance-nan", GEN + " --text walk --guidance nan", "--guidance",
        "`--guidance nan`"),
    Cli("generate-guidance-inf", GEN + " --text walk --guidance inf", "--guidance",
        "`--guidance inf`"),
    Cli("generate-guidance-huge", GEN + " --text walk --guidance 1e308", "guidance_scale",
        "`--guidance 1e308` (the guided logits overflowed: drew the worst tokens)"),
    Cli("generate-temperature-negative", GEN + " --text walk --temperature -1", "--temperature",
        "a negative temperature"),
    Cli("generate-bvh-fps-zero", GEN + " --text walk --bvh-fps 0", "--bvh-fps", "a BVH frame rate of 0"),
    Cli("generate-steps-zero", GEN + " --text walk --steps 0", "--steps", "0 decoding steps"),
    Cli("generate-steps-huge", GEN + " --text walk --steps 1000000000", "steps must be a whole "
        "number in [1, 1000]", "a billion decoding steps (took 18 GB before it was killed)"),
    Cli("generate-seed-huge", GEN + " --text walk --seed 99999999999999999999999", "--seed",
        "a seed beyond 64 bits (was a traceback from torch)"),
    Cli("generate-length-huge", GEN + " --text walk --length 100000000000000000000000", "--length",
        "a length beyond 64 bits (was a traceback from torch)"),
    Cli("generate-length-fraction", GEN + " --text walk --length 40.7", "--length",
        "`--length 40.7` (was truncated to 40)"),
    Cli("generate-length-not-multiple", GEN + " --text walk --length 30", "multiples of 4",
        "a length that is not a multiple of 4 frames"),
    Cli("generate-length-too-long", GEN + " --text walk --length 10000", "multiples of 4",
        "a length beyond the model's 196 frames"),
    Cli("generate-length-count", GEN + " --text walk --text run --length 40 --length 40 "
        "--length 40", "--length", "three lengths for two prompts"),
    Cli("generate-durations-word", GEN + " --text walk --durations 1,long", "--durations",
        "`--durations 1,long`"),
    Cli("generate-durations-count", GEN + " --text walk --durations 1 --durations 1",
        "--durations", "two duration lists for one prompt"),
    Cli("generate-durations-untimed", GEN + " --text walk --durations 1", "segment timing",
        "durations for a model trained without segment timing"),
    Cli("compose-durations-count", "compose --model {bundle} --out {tmp}/long --text walk "
        "--length 40 --durations 1 --durations 1", "--durations",
        "two duration lists for one part"),
    Cli("generate-device-cuda", GEN + " --text walk --device cuda:7", "--device",
        "a CUDA device on a machine without one"),
    Cli("generate-device-bogus", GEN + " --text walk --device toaster", "--device",
        "a device name torch does not know"),
    Cli("generate-formats", GEN + " --text walk --formats gif,fbx", "--formats",
        "an unknown output format"),
    Cli("generate-out-is-file", "generate --model {bundle} --text walk --out {file}",
        "--out", "`--out` naming an existing file"),
    Cli("generate-out-through-file", "generate --model {bundle} --text walk --out {file}/sub",
        "is a file, not a directory", "`--out` inside a file (was refused after the generation)"),
    Cli("generate-out-empty", "generate --model {bundle} --text walk --out {empty}",
        "argument --out: expected a folder", "`--out \"\"` (an unset variable; wrote into the "
        "current folder)"),
    Cli("generate-out-foreign-prompts", "generate --model {bundle} --text walk --out {theirs}",
        "not a prompts.json written by segmo", "`--out` holding a prompts.json of the user's"),
    Cli("compose-out-user-file", "compose --model {bundle} --text walk --length 40 --out {notes}",
        "sample_00.bvh: a file that segmo did not write",
        "`--out` holding the user's `sample_00.bvh` (was replaced by the output)"),
    Cli("edit-weight-twice", "edit --model {bundle} --source-text walk --mode reweight "
        "--weight 1=2 --weight 1=0.5 --out {tmp}/e", "--weight names one segment twice",
        "`--weight 1=2 --weight 1=0.5` (the last won without a word)"),
    Cli("edit-weight-with-swap", "edit --model {bundle} --source-text walk --target-text run "
        "--weight 2=2 --out {tmp}/e", "--weight is for --mode reweight",
        "`--weight` with `--mode swap` (was ignored)"),
    Cli("edit-reweight-inject-until", "edit --model {bundle} --source-text walk --mode reweight "
        "--weight 1=2 --inject-until 0.2 --out {tmp}/e", "--inject-until is for --mode swap",
        "`--inject-until` with `--mode reweight` (was ignored)"),
    Cli("edit-reweight-target-text", "edit --model {bundle} --source-text walk --target-text run "
        "--mode reweight --weight 1=2 --out {tmp}/e", "--target-text is for --mode swap",
        "`--target-text` other than the source's with `--mode reweight` (generated the other "
        "text's motion)"),
    Cli("edit-weight-superscript", "edit --model {bundle} --source-text walk --mode reweight "
        "--weight ²=2 --out {tmp}/e", "weights key '²'",
        "`--weight ²=2`, a digit int() refuses (was a traceback)"),
    Cli("edit-weight-huge", "edit --model {bundle} --source-text walk --mode reweight "
        "--weight {huge}=2 --out {tmp}/e", "weights key '999",
        "`--weight` of a 5000-digit segment, more than int() reads (was a ValueError traceback)"),
    Cli("generate-model-missing", "generate --model {tmp}/nope --text walk --out {tmp}/g",
        "--model", "a model folder that does not exist"),
    Cli("generate-model-is-stage", "generate --model {bundle}/mask --text walk --out {tmp}/g",
        "segmo.json", "a single stage instead of a bundle"),
    Cli("generate-bundle-residual-loop", "generate --model {residual_loop} --text walk --out "
        "{tmp}/g", "residual stage is not a model directory", "a bundle whose residual stage "
        "is a link to itself (was left out without a word)"),
    Cli("generate-bundle-deep-json", "generate --model {deep_bundle_json} --text walk --out "
        "{tmp}/g", "nested too deeply", "a segmo.json of 200,000 '[' (was a RecursionError)"),
    Cli("generate-bundle-json", "generate --model {bad_bundle_json} --text walk --out {tmp}/g",
        "segmo.json:2", "invalid JSON in segmo.json"),
    Cli("generate-bundle-format", "generate --model {bad_format} --text walk --out {tmp}/g",
        "format 99", "a segmo.json of an unknown format"),
    Cli("generate-bundle-guidance", "generate --model {bad_guidance} --text walk --out {tmp}/g",
        "guidance_scale", "a segmo.json whose guidance scale is a string"),
    Cli("generate-bundle-fps", "generate --model {bad_fps} --text walk --out {tmp}/g",
        "segmo.json: 'fps' must be a frame rate", "a segmo.json whose fps is a string (failed "
        "when the GIF was written, after the npy files)"),
    Cli("generate-bundle-text-segmenter", "generate --model {bad_text_segmenter} --text walk "
        "--out {tmp}/g", "segmo.json: 'text_segmenter'", "a segmo.json naming an unknown text "
        "segmenter"),
    Cli("generate-bundle-motion-segmenter", "generate --model {bad_motion_segmenter} --text walk "
        "--out {tmp}/g", "segmo.json: 'motion_segmenter'", "a segmo.json whose motion segmenter "
        "is a number"),
    Cli("generate-bundle-steps", "generate --model {bad_steps} --text walk --out {tmp}/g",
        "segmo.json: steps", "a segmo.json with 0 decoding steps"),
    Cli("generate-bundle-no-text-encoder", "generate --model {no_text_encoder} --text walk "
        "--out {tmp}/g", "segmo.json: missing key 'text_encoder'", "a segmo.json without "
        "'text_encoder' (was a TypeError)"),
    Cli("generate-bundle-skeleton-list", "generate --model {skeleton_list} --text walk "
        "--out {tmp}/g", "segmo.json: 'skeleton'", "a segmo.json whose skeleton is a list (was "
        "a TypeError: unhashable type)"),
    Cli("generate-residual-layers", GEN + " --text walk --residual-guided-layers -1",
        "--residual-guided-layers", "a negative number of guided residual layers"),
    Cli("generate-config-json", "generate --model {bad_config_json} --text walk --out {tmp}/g",
        "mask/config.json:1", "invalid JSON in a stage's config.json"),
    Cli("generate-config-field", "generate --model {extra_field} --text walk --out {tmp}/g",
        "'wings'", "an unknown field in a stage's config.json"),
    Cli("generate-config-type", "generate --model {bad_type} --text walk --out {tmp}/g",
        "mask/config.json", "a config field of the wrong type"),
    Cli("generate-config-huge", "generate --model {huge_config} --text walk --out {tmp}/g",
        "the weights do not fit", "a config edited to sizes of terabytes (its model was built "
        "before the weights were checked: a 2.9 GB peak for dim 4096)"),
    Cli("generate-weights-garbage", "generate --model {bad_weights} --text walk --out {tmp}/g",
        "model.safetensors", "a weights file that is not safetensors"),
    Cli("generate-weights-shape", "generate --model {bad_shape} --text walk --out {tmp}/g",
        "do not fit", "weights that do not fit the config"),
    Cli("generate-weights-nan", "generate --model {nan_weights} --text walk --out {tmp}/g",
        "NaN or inf", "weights holding NaN (a diverged run)"),
    Cli("generate-stage-missing", "generate --model {no_mask} --text walk --out {tmp}/g",
        "mask", "a bundle without its mask stage"),
    Cli("generate-stage-folder-missing", "generate --model {no_residual} --text walk --out "
        "{tmp}/g", "no_residual/residual: missing, but segmo.json lists", "a bundle whose "
        "residual folder was lost in a copy (generated without it, without a word)"),
    # -- segmo ground
    Cli("ground-motion-nan", GROUND + " --motion {nan_motion}", "nan_motion.npy",
        "a motion with a NaN frame"),
    Cli("ground-motion-huge", GROUND + " --motion {huge_motion}", "huge_motion.npy",
        "a finite but absurd motion (1e30)"),
    Cli("ground-motion-pickle", GROUND + " --motion {pickle}", "pickle.npy",
        "a .npy holding a pickled object"),
    Cli("ground-motion-text", GROUND + " --motion {text_file}", "notes.txt",
        "a text file as motion"),
    Cli("ground-motion-npz", GROUND + " --motion {npz}", "archive.npy: an .npz archive",
        "an .npz archive named .npy (was an AttributeError)"),
    Cli("render-npz", "render {npz} --out {tmp}/r.gif", "archive.npy: an .npz archive",
        "an .npz archive named .npy (was an AttributeError)"),
    Cli("ground-motion-dir", GROUND + " --motion {tmp}", "is a directory", "a folder as motion"),
    Cli("ground-motion-joints", GROUND + " --motion {joints}", "joints", "joints instead of features"),
    Cli("ground-motion-dim", GROUND + " --motion {wrong_dim}", "(170, 100)",
        "features of the wrong width"),
    Cli("ground-motion-short", GROUND + " --motion {short_motion}", "frames",
        "a 2-frame motion"),
    Cli("ground-motion-long", GROUND + " --motion {long_motion}", "frames",
        "a motion longer than the model takes"),
    Cli("ground-motion-strings", GROUND + " --motion {strings}", "strings.npy",
        "an array of strings"),
    Cli("ground-window-zero", GROUND + " --motion {motion} --window 0", "--window",
        "a window of 0 tokens"),
    Cli("ground-stride-zero", GROUND + " --motion {motion} --stride 0", "--stride",
        "a stride of 0 tokens"),
    Cli("ground-segments-empty", GROUND + " --motion {motion} --segments ##", "segment 0",
        "empty text segments (`--segments ##`)"),
    Cli("ground-segments-many", GROUND + " --motion {motion} --segments a#b#c#d#e#f",
        "6 segments", "more segments than the model takes"),
    Cli("ground-stride-ordered", GROUND + " --motion {motion} --stride 7",
        "--stride is for --search window", "`--stride` with the ordered search (was ignored)"),
    Cli("ground-min-tokens-window", GROUND + " --motion {motion} --window 5 --min-tokens 3",
        "--min-tokens is for --search ordered or spans", "`--min-tokens` with the window "
        "search (was ignored)"),
    Cli("ground-out-link", GROUND + " --motion {motion} --out {map_link}",
        "a symbolic link to notes.txt; pass --overwrite", "`--out` a link to a file of the "
        "user's (was written through: the file became a PNG)"),
    Cli("ground-out-file", GROUND + " --motion {motion} --out {old_map}",
        "exists; pass --overwrite", "`--out` an existing image (was replaced without a word)"),
    # -- segmo bundle
    Cli("bundle-wrong-kind", "bundle --tokenizer {bundle}/mask --mask {bundle}/mask --out {tmp}/b",
        "'rvq'", "a mask stage as tokenizer"),
    Cli("bundle-missing-stage", "bundle --tokenizer {bundle}/tokenizer --mask {tmp}/nope "
        "--out {tmp}/b", "--mask", "a stage folder that does not exist"),
    Cli("bundle-guidance-nan", "bundle --tokenizer {bundle}/tokenizer --mask {bundle}/mask "
        "--guidance nan --out {tmp}/b", "--guidance", "`--guidance nan`"),
    Cli("bundle-out-is-file", "bundle --tokenizer {bundle}/tokenizer --mask {bundle}/mask "
        "--out {file}", "--out", "`--out` naming an existing file"),
    Cli("bundle-out-empty", "bundle --tokenizer {bundle}/tokenizer --mask {bundle}/mask "
        "--out {empty} --overwrite", "argument --out: expected a folder, got an empty string",
        "`--out \"\"` (an unset variable) with `--overwrite` (the current folder's files were "
        "replaced by the bundle)"),
    Cli("bundle-out-parent", "bundle --tokenizer {bundle}/tokenizer --mask {bundle}/mask "
        "--out .. --overwrite", "..: holds the current folder", "`--out ..` with `--overwrite` "
        "(the folder above was replaced, the current one with it)"),
    Cli("bundle-push-to-hub-id", "bundle --tokenizer {bundle}/tokenizer --mask {bundle}/mask "
        "--out {tmp}/bh --push-to-hub nope", "repo_id must look like 'owner/name'",
        "`--push-to-hub` with no repository id (was refused after the bundle was written)"),
    Cli("bundle-segmenter", "bundle --tokenizer {bundle}/tokenizer --mask {bundle}/mask "
        "--segmenter llama --out {tmp}/b", "--segmenter", "an unknown text segmenter"),
    Cli("bundle-stage-meta", "bundle --tokenizer {bundle}/tokenizer --mask {meta_string}/mask "
        "--out {tmp}/b", "mask/config.json: 'meta'", "a stage whose config.json's meta is a "
        "string (was an AttributeError)"),
    Cli("bundle-tokenizer-bad-id", "bundle --tokenizer foo/bar..baz --mask {bundle}/mask "
        "--out {tmp}/b", "foo/bar..baz", "a tokenizer that is neither a folder nor a valid hub "
        "id (was an HFValidationError traceback)"),
    Cli("bundle-stage-json", "bundle --tokenizer {bundle}/tokenizer --mask {bad_config_json}/mask "
        "--out {tmp}/b", "config.json:1", "a stage whose config.json is invalid JSON"),
    # -- segmo render
    Cli("render-stride-huge", "render {motion} --out {tmp}/r.gif --stride 100000", "stride 100000",
        "frames of 5,000 s (a 16-bit GIF delay; was a struct.error traceback)"),
    Cli("render-nan", "render {nan_motion} --out {tmp}/r.gif", "nan_motion.npy",
        "a motion with a NaN frame"),
    Cli("render-huge", "render {huge_motion} --out {tmp}/r.gif", "huge_motion.npy",
        "a finite but absurd motion (1e30)"),
    Cli("render-pickle", "render {pickle} --out {tmp}/r.gif", "pickle.npy",
        "a .npy holding a pickled object"),
    Cli("render-empty", "render {empty_motion} --out {tmp}/r.gif", "0 frames",
        "a motion with 0 frames"),
    Cli("render-shape", "render {wrong_dim} --out {tmp}/r.gif", "(170, 100)",
        "an array of the wrong shape"),
    Cli("render-suffix", "render {motion} --out {tmp}/r.txt", "--out", "an output that is no GIF/MP4"),
    Cli("render-fps-zero", "render {motion} --out {tmp}/r.gif --fps 0", "--fps", "`--fps 0`"),
    Cli("render-fps-nan", "render {motion} --out {tmp}/r.gif --fps nan", "--fps", "`--fps nan`"),
    Cli("render-stride-zero", "render {motion} --out {tmp}/r.gif --stride 0", "--stride",
        "`--stride 0`"),
    Cli("render-missing", "render {tmp}/nope.npy --out {tmp}/r.gif", "nope.npy",
        "a file that does not exist"),
    Cli("render-mean-shape", "render {motion} --out {tmp}/r.gif --mean {motion} --std {motion}",
        "mean must have shape (263,)", "`--mean`/`--std` of a motion's shape (were broadcast)"),
    Cli("render-out-dir", "render {motion} --out {gif_dir}", "is a directory",
        "`--out` naming a folder that ends in .gif (refused after the rendering)"),
    Cli("render-out-through-file", "render {motion} --out {file}/r.gif", "is a file, not a "
        "directory", "`--out` inside a file (refused after the rendering)"),
    Cli("render-mean-alone", "render {motion} --out {tmp}/r.gif --mean {motion}", "--mean",
        "`--mean` without `--std`"),
    # -- segmo synth
    Cli("synth-zero-motions", "synth --out {tmp}/s --num-motions 0", "--num-motions",
        "0 motions"),
    Cli("synth-seed-negative", "synth --out {tmp}/s --seed -1", "--seed", "a negative seed"),
    Cli("synth-workers-zero", "synth --out {tmp}/s --workers 0", "--workers", "0 workers"),
    Cli("synth-out-is-file", "synth --out {file} --num-motions 3", "notes.txt",
        "`--out` naming an existing file"),
    Cli("synth-foreign-folder", "synth --out {foreign} --num-motions 3", "not empty",
        "a folder holding someone else's files"),
    Cli("synth-derived-data", "synth --out {corpus} --num-motions 7", "text_features",
        "a rebuild that would delete text features built in the folder"),
    Cli("synth-out-empty", "synth --out {empty} --num-motions 3 --overwrite",
        "argument --out: expected a folder", "`--out \"\"` with `--overwrite` (was 'Device or "
        "resource busy' after the build, leaving a .tmp- corpus in the current folder)"),
    Cli("synth-out-current", "synth --out . --num-motions 3 --overwrite",
        ".: is the current folder", "`--out .` with `--overwrite`"),
    # -- segmo evaluate
    Cli("evaluate-model-required", "evaluate --data {corpus} --evaluator {tmp} --out {tmp}/e",
        "--model", "no `--model` and no `--real-only`"),
    Cli("evaluate-data-missing", "evaluate --real-only --data {tmp}/nope --evaluator {tmp} "
        "--out {tmp}/e", "--data", "a dataset folder that does not exist"),
    Cli("evaluate-repeats-zero", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --repeats 0", "--repeats", "0 repeats"),
    Cli("evaluate-batch-one", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --batch-size 1", "--batch-size", "batches of 1 (R-precision needs 2)"),
    Cli("evaluate-split", "evaluate --real-only --data {corpus} --evaluator {tmp} --out {tmp}/e "
        "--split dev", "--split", "a split without a split file"),
    Cli("evaluate-window", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --grounding-window 4,x", "--grounding-window", "a bad grounding window"),
    Cli("evaluate-window-superscript", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --grounding-window ²", "--grounding-window", "`--grounding-window ²`, "
        "a digit int() refuses (was a ValueError traceback)"),
    Cli("evaluate-window-huge", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --grounding-window {huge}", "--grounding-window", "`--grounding-window` of "
        "5000 digits, more than int() reads (was a ValueError traceback)"),
    Cli("evaluate-evaluator-kind", "evaluate --real-only --data {corpus} --evaluator "
        "{bundle}/mask --out {tmp}/e", "--evaluator", "a mask stage as evaluator"),
    Cli("evaluate-evaluator-kind-list", "evaluate --real-only --data {corpus} --evaluator "
        "{kind_list}/mask --out {tmp}/e", "config.json: 'kind'", "a config.json whose kind is "
        "a list (was a TypeError: unhashable type)"),
    Cli("evaluate-device", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --device toaster", "--device toaster", "a device torch does not know"),
    Cli("evaluate-threads-huge", "evaluate --real-only --data {corpus} --evaluator {tmp} "
        "--out {tmp}/e --threads 100000000000000", "--threads", "10^14 threads (was a traceback)"),
    Cli("evaluate-compare-missing", "evaluate --compare {tmp}/nope --out {tmp}/e",
        "metrics.json", "`--compare` of a folder without metrics.json"),
    Cli("evaluate-compare-json", "evaluate --compare {bad_metrics} --out {tmp}/e",
        "metrics.json:1", "`--compare` of an invalid metrics.json"),
    Cli("evaluate-compare-shape", "evaluate --compare {odd_metrics} --out {tmp}/e",
        "odd/metrics.json: not a metrics.json", "`--compare` of a metrics.json of other shape"),
    Cli("evaluate-compare-row", "evaluate --compare {row_metrics} --out {tmp}/e",
        "generation.generated.fid: expected a number", "`--compare` of a metric of another "
        "shape (was a KeyError traceback)"),
    Cli("evaluate-compare-empty", "evaluate --compare {empty_metrics} --out {tmp}/e",
        "no metrics.json given has generation rows", "`--compare` of a metrics.json without rows"),
    # -- segmo export, fit, validate, test (more of fit: tests/test_training_cli.py)
    Cli("export-missing", "export {tmp}/none.ckpt --out {tmp}/m", "none.ckpt",
        "a checkpoint that does not exist"),
    Cli("export-garbage", "export {junk_ckpt} --out {tmp}/m", "junk.ckpt",
        "a file that is not a checkpoint"),
    Cli("export-not-lightning", "export {list_ckpt} --out {tmp}/m", "list.ckpt",
        "a torch file that is no Lightning checkpoint"),
    Cli("export-bad-task", "export {junk_ckpt} --task segmo.tasks.nope.Task --out {tmp}/m",
        "junk.ckpt", "`--task` naming a class that does not exist"),
    Cli("export-out-empty", "export {junk_ckpt} --out {empty} --overwrite",
        "argument --out: expected a folder", "`--out \"\"` with `--overwrite` (the current "
        "folder's files were replaced by the model)"),
    Cli("fit-missing-config", "fit --config {tmp}/none.yaml", "none.yaml",
        "a YAML config that does not exist"),
    Cli("fit-data-missing", "fit --config configs/rvq/synthetic.yaml --data.root {tmp}/nope",
        "data.init_args.root", "a dataset folder that does not exist"),
    Cli("validate-data-missing", "validate --config configs/rvq/synthetic.yaml --data.root "
        "{tmp}/nope", "data.init_args.root", "`validate` on a dataset folder that does not exist"),
    Cli("test-data-file", "test --config configs/rvq/synthetic.yaml --data.root {file}",
        "data.init_args.root", "`test` with a file as the dataset folder"),
    # -- segmo demo
    Cli("demo-out-is-file", "demo --out {file}", "--out", "`--out` naming an existing file"),
    Cli("serve-model-missing", "serve --model {tmp}/nope", "no such directory",
        "a model folder that does not exist"),
    Cli("demo-budget", "demo --out {tmp}/d --budget huge", "--budget", "an unknown budget"),
    Cli("demo-seed", "demo --out {tmp}/d --seed -3", "--seed", "a negative seed"),
]


@dataclass(frozen=True)
class Api:
    """`call(model, world)` must raise `error` with `names` in its message."""

    id: str
    call: object
    error: type
    names: str
    what: str


def _motion(world):
    return np.load(world["motion"])


API_CASES = [
    Api("api-lengths-fraction", lambda m, w: m.generate(["walk"], [40.7]), SegmoError, "40.7",
        "`generate(lengths=[40.7])` (was truncated to 40)"),
    Api("api-lengths-bool", lambda m, w: m.generate(["walk"], [True]), SegmoError, "True",
        "`generate(lengths=[True])`"),
    Api("api-lengths-nan", lambda m, w: m.generate(["walk"], float("nan")), SegmoError, "nan",
        "`generate(lengths=nan)`"),
    Api("api-lengths-huge", lambda m, w: m.generate(["walk"], 10**30), SegmoError,
        "a length of 1000000000000000000000000000000 frames is out of range",
        "`generate(lengths=10**30)` (was a traceback from torch)"),
    Api("api-lengths-count", lambda m, w: m.generate(["walk", "run"], [40, 40, 40]), SegmoError,
        "3 lengths for 2 texts", "three lengths for two texts"),
    Api("api-text-none", lambda m, w: m.generate([None], [40]), SegmoError, "text 0",
        "a prompt that is None"),
    Api("api-text-empty-list", lambda m, w: m.generate([], [40]), SegmoError, "empty",
        "no prompts"),
    Api("api-text-none-list", lambda m, w: m.generate(None, [40]), SegmoError,
        "expected a list of strings", "`generate(None)` (said 'texts is empty')"),
    Api("api-generator-int", lambda m, w: m.generate(["walk"], [40], generator=0), SegmoError,
        "generator must be a torch.Generator", "`generate(generator=0)` (was an AttributeError)"),
    Api("api-compose-generator", lambda m, w: m.compose([("walk", 40)], generator="x"),
        SegmoError, "generator must be a torch.Generator", "`compose(generator='x')`"),
    Api("api-encode-texts-number", lambda m, w: m.encode_texts([1]), SegmoError,
        "text 0 is a int, not a string", "`encode_texts([1])` (was a TypeError)"),
    Api("api-encode-texts-surrogate", lambda m, w: m.encode_texts(["\ud800 walk"]), SegmoError,
        "text 0 ('\\ud800 walk') is not valid Unicode",
        "`encode_texts` of a text with a lone surrogate (was a TypeError from the tokenizer)"),
    Api("api-sample-lengths-surrogate", lambda m, w: m.sample_lengths(["\ud800 walk"]), SegmoError,
        "is not valid Unicode", "`sample_lengths` of a lone surrogate (was a TypeError)"),
    Api("api-sample-lengths-no-words", lambda m, w: m.sample_lengths(["..."]), SegmoError,
        "holds no words", "`sample_lengths(['...'])` (drew a length for no motion)"),
    Api("api-edit-text-number",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), 7), SegmoError,
        "target_text must be a string", "`edit_text(source, 7)` (was a TypeError)"),
    Api("api-ground-window-fraction", lambda m, w: m.ground("walk", _motion(w), window=2.5),
        SegmoError, "window=2.5", "`ground(window=2.5)` (was a TypeError)"),
    Api("api-guidance-nan", lambda m, w: m.generate(["walk"], [40], guidance_scale=float("nan")),
        SegmoError, "guidance_scale", "`guidance_scale=nan`"),
    Api("api-steps-fraction", lambda m, w: m.generate(["walk"], [40], steps=2.5), SegmoError,
        "steps", "`steps=2.5`"),
    Api("api-top-k-zero", lambda m, w: m.generate(["walk"], [40], top_k_ratio=0.0), SegmoError,
        "top_k_ratio", "`top_k_ratio=0`"),
    Api("api-sampler", lambda m, w: m.generate(["walk"], [40], sampler="beam"), SegmoError,
        "sampler", "an unknown sampler"),
    Api("api-durations-untimed", lambda m, w: m.generate(["walk"], [40], durations=[[1]]),
        SegmoError, "segment timing", "`generate(durations=...)` on a model without timing"),
    Api("api-compose-part-shape", lambda m, w: m.compose([("walk", 40, [1], "run")]),
        SegmoError, "(text, frames, durations)", "a part of four items"),
    Api("api-segments-shape", lambda m, w: m.generate(["walk", "run"], [40], segments=[["walk"]]),
        SegmoError, "segments", "one segment list for two prompts"),
    Api("api-segments-number", lambda m, w: m.generate(["walk"], [40], segments=5), SegmoError,
        "segments must be one list of strings per text", "`generate(segments=5)` (was a "
        "TypeError)"),
    Api("api-segments-generator",
        lambda m, w: m.generate(["walk"], [40], segments=(s for s in [["walk"]])), SegmoError,
        "segments must be one list of strings per text", "segments as a generator (was a "
        "TypeError)"),
    Api("api-edit-span-order", lambda m, w: m.edit(_motion(w), (40, 8), "run"), SegmoError,
        "span", "`edit(span=(40, 8))`"),
    Api("api-edit-span-fraction", lambda m, w: m.edit(_motion(w), (0.5, 8), "run"), SegmoError,
        "span", "`edit(span=(0.5, 8))`"),
    Api("api-generate-not-unicode", lambda m, w: m.generate(["walk \udcff then run"], [40]),
        SegmoError, "not valid Unicode", "a prompt with bytes that are not UTF-8 (was a "
        "TypeError from the tokenizer)"),
    Api("api-edit-text-weights-with-swap",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), "walk, then jump",
                                 weights={2: 2.0}),
        SegmoError, "weights are for mode 'reweight'", "weights with mode swap (were ignored)"),
    Api("api-edit-text-reweight-target",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), "jump, then sit",
                                 mode="reweight", weights={1: 2.0}),
        SegmoError, "mode 'reweight' edits the source's own text", "a reweight with another "
        "target text (generated that text's motion, not the source's reweighted)"),
    Api("api-edit-text-reweight-inject",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), mode="reweight",
                                 weights={1: 2.0}, inject_until=0.2),
        SegmoError, "inject_until is for modes 'swap', 'add' and 'refine'",
        "`inject_until` with mode reweight (was ignored)"),
    Api("api-edit-text-ambiguous-key",
        lambda m, w: m.edit_text(m.generate(["a man walks, then a man runs"], [40]),
                                 mode="reweight", weights={"a": 2.0}),
        SegmoError, "is part of segments [1, 2]", "a weights key found in two segments (took "
        "the first)"),
    Api("api-edit-text-empty-key",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), mode="reweight",
                                 weights={"": 2.0}),
        SegmoError, "names no segment", "an empty weights key (took segment 1)"),
    Api("api-edit-text-huge-key",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), mode="reweight",
                                 weights={"segment " + w["huge"]: 2.0}),
        SegmoError, "must be 'segment k'", "a weights key 'segment 999…' of 5000 digits, more "
        "than int() reads (was a ValueError traceback)"),
    Api("api-compose-no-context",
        lambda m, w: m.compose([("walk", 40), ("run", 40)], m.max_frames - 12), SegmoError,
        "too little room for context", "a transition that leaves one token of context (was a "
        "RuntimeError)"),
    Api("api-save-spans-count",
        lambda m, w: m.generate(["walk", "run"], [40, 40]).save(
            w["tmp"] / "spans", formats=("gif",), spans=[[(0, 40)]]), SegmoError,
        "spans must be one list of (start, end) frame spans per sample (2)",
        "`save(spans=...)` with fewer span lists than samples (was an IndexError)"),
    Api("api-save-spans-segments",
        lambda m, w: m.generate(["walk", "run"], [40, 40]).save(
            w["tmp"] / "spans", formats=("gif",), spans=[[(0, 40)], [(0, 20), (20, 40)]]),
        SegmoError, "spans[1] must be one (start, end) per segment of sample 1",
        "`save(spans=...)` with two spans for a sample of one segment (no label, without a word)"),
    Api("api-save-spans-words",
        lambda m, w: m.generate(["walk"], [40]).save(
            w["tmp"] / "spans", formats=("gif",), spans=[[("start", "end")]]), SegmoError,
        "spans[0]: span must be (start, end) whole frames",
        "`save(spans=...)` of words, not frames (was a ValueError from the GIF)"),
    Api("api-from-pretrained-none", lambda m, w: SegMo.from_pretrained(None), SegmoError,
        "expected a model folder or a hub id", "`SegMo.from_pretrained(None)` (was a TypeError)"),
    Api("api-from-pretrained-long-name", lambda m, w: SegMo.from_pretrained("a" * 5000),
        SegmoError, "File name too long", "a 5,000-character folder name (was an OSError)"),
    Api("api-word-texts-bogus", lambda m, w: m.word_texts(["walk"], word_text="bogus"),
        SegmoError, "word_text must be 'caption' or 'segments'", "`word_texts(word_text=\"bogus\")` "
        "(was accepted)"),
    Api("api-segment-texts-none", lambda m, w: m.segment_texts(None), SegmoError,
        "expected a list of strings", "`segment_texts(None)` (was a TypeError)"),
    Api("api-ground-min-tokens-beyond-motion",
        lambda m, w: m.ground("walk", _motion(w), search="spans", min_tokens=1000), SegmoError,
        "min_tokens=1000 tokens; the motion has 12", "`ground(search=\"spans\", "
        "min_tokens=1000)` (was cut to the whole motion)"),
    Api("api-ground-stride-ordered", lambda m, w: m.ground("walk", _motion(w), stride=7),
        SegmoError, "stride=7 is for search='window'", "`ground(stride=7)` with the ordered "
        "search (was ignored)"),
    Api("api-ground-window-bool", lambda m, w: m.ground("walk", _motion(w), window=True),
        SegmoError, "not a bool", "`ground(window=True)` (was a window of 1)"),
    Api("api-retrieve-texts-string", lambda m, w: m.retrieve_texts(_motion(w), "walk"),
        SegmoError, "candidates must be a list of texts", "`retrieve_texts(motion, \"walk\")` "
        "(ranked the letters)"),
    Api("api-retrieve-texts-span-fraction",
        lambda m, w: m.retrieve_texts(_motion(w), ["walk"], span=(0.9, 7.9)), SegmoError,
        "span must be (start, end) whole frames", "`retrieve_texts(span=(0.9, 7.9))` (was cut "
        "to (0, 7))"),
    Api("api-ground-attention-segments-string",
        lambda m, w: m.ground("walk then run", _motion(w), method="attention", segments="ab"),
        SegmoError, "segments must be a list of texts", "`ground(method=\"attention\", "
        "segments=\"ab\")` (grounded 'a' and 'b')"),
    Api("api-embed-normalized-nan",
        lambda m, w: m.embed_segments(["walk"], [np.full_like(_motion(w), np.nan)],
                                      normalized=True),
        SegmoError, "not a motion", "`embed_segments(normalized=True)` of NaN (returned NaN)"),
    Api("api-edit-text-inject-bool",
        lambda m, w: m.edit_text(m.generate(["walk, then run"], [40]), "walk, then jump",
                                 inject_until=True),
        SegmoError, "inject_until must be in [0, 1], got True", "`inject_until=True` (was read "
        "as 1.0)"),
    Api("api-edit-composition",
        lambda m, w: m.edit(m.compose([("walk", 120), ("run", 120)]), (0, 8), "wave"), SegmoError,
        "more than the 196 the model reads at once", "`edit` of a composition longer than the "
        "model's frames (was a ValueError about the 'Trunk')"),
    Api("api-compose-too-long", lambda m, w: m.compose([("walk", 196)] * 200), SegmoError,
        "more than 20 minutes", "200 parts of 196 frames (time and memory grow without bound)"),
    Api("api-compose-too-long-floats", lambda m, w: m.compose([("walk", 196.0)] * 200),
        SegmoError, "more than 20 minutes", "200 parts of 196.0 frames (passed the limit: "
        "only int frames were counted)"),
    Api("api-compose-short-float", lambda m, w: m.compose([("walk", 4.0), ("run", 40)]),
        SegmoError, "needs at least 20 frames", "a part of 4.0 frames (was a RuntimeError, "
        "tensor sizes)"),
    Api("api-ground-nan", lambda m, w: m.ground("walk", np.load(w["nan_motion"])), SegmoError,
        "frame 5", "`ground` on a motion with a NaN frame"),
    Api("api-ground-complex", lambda m, w: m.ground("walk", _motion(w).astype(np.complex64)),
        SegmoError, "complex", "`ground` on a complex motion (the imaginary part was dropped)"),
    Api("api-ground-strings", lambda m, w: m.ground("walk", [["a"] * 263] * 8), SegmoError,
        "numeric", "`ground` on a list of strings"),
    Api("api-retrieve-empty", lambda m, w: m.retrieve_texts(_motion(w), []), SegmoError,
        "candidate", "`retrieve_texts` with no candidates"),
    Api("api-retrieve-motions-none", lambda m, w: m.retrieve_motions("walk", None), SegmoError,
        "motions must be a list", "`retrieve_motions(text, None)` (was a TypeError)"),
    Api("api-retrieve-motions-generator",
        lambda m, w: m.retrieve_motions("walk", (x for x in [_motion(w)])), SegmoError,
        "motions must be a list", "`retrieve_motions` of a generator (was a TypeError)"),
    Api("api-retrieve-top-k", lambda m, w: m.retrieve_texts(_motion(w), ["walk"], top_k=0),
        SegmoError, "top_k", "`retrieve_texts(top_k=0)`"),
    Api("api-embed-length-negative",
        lambda m, w: m.embed_segments(["walk"], _motion(w)[None], lengths=[-8]), SegmoError,
        "lengths must be in [1, 48]", "`embed_segments` of a (b, t, d) tensor with a negative "
        "length (was cut 8 frames short)"),
    Api("api-embed-length-beyond",
        lambda m, w: m.embed_segments(["walk"], _motion(w)[None], lengths=[400]), SegmoError,
        "lengths must be in [1, 48]", "`embed_segments` with a length beyond the tensor's "
        "frames (was the whole tensor)"),
    Api("api-embed-pairs-span-fraction",
        lambda m, w: m.embed_pairs(["walk, then run"], [_motion(w)], [[[0.9, 4.9], [4, 12]]]),
        SegmoError, "spans[0][0]: span must be (start, end) whole tokens",
        "`embed_pairs` span (0.9, 4.9) (was cut to (0, 4))"),
    Api("api-embed-pairs-span-negative",
        lambda m, w: m.embed_pairs(["walk, then run"], [_motion(w)], [[[-3, 4], [4, 12]]]),
        SegmoError, "spans[0][0]: span must satisfy 0 ≤ start < end ≤ 12 tokens",
        "`embed_pairs` span (-3, 4) (was read as (0, 4))"),
    Api("api-embed-pairs-span-reversed",
        lambda m, w: m.embed_pairs(["walk, then run"], [_motion(w)], [[[6, 2], [4, 12]]]),
        SegmoError, "spans[0][0]: span must satisfy 0 ≤ start < end ≤ 12 tokens",
        "`embed_pairs` span (6, 2) (its segment was left out without a word)"),
    Api("api-embed-one-motion", lambda m, w: m.embed_segments(["walk"], _motion(w)), SegmoError,
        "wrap one motion in a list", "`embed_segments` of one (t, d) motion, not a list"),
    Api("api-embed-text-string", lambda m, w: m.embed_segments("walk", [_motion(w)]),
        SegmoError, "expected a list of strings", "`embed_segments` of a string, not a list "
        "(was split into letters)"),
    Api("api-from-pretrained-missing", lambda m, w: SegMo.from_pretrained(w["tmp"] / "nope"),
        FileNotFoundError, "no such model folder", "`from_pretrained` of a missing folder"),
    Api("api-from-pretrained-newer-stage-format", lambda m, w: SegMo.from_pretrained(w["newer_stage"]),
        SegmoError, "reads format 1 and older", "a stage written in a newer format by a newer segmo"),
    Api("api-from-pretrained-hub-offline", lambda m, w: SegMo.from_pretrained("someone/not-cached"),
        SegmoError, "not in the Hugging Face cache", "a hub id that is not cached, offline"),
    Api("api-from-pretrained-device", lambda m, w: SegMo.from_pretrained(w["bundle"],
                                                                         device="cuda:3"),
        SegmoError, "cuda:3", "`from_pretrained(device='cuda:3')` without a GPU"),
    Api("api-render-nan", lambda m, w: __import__("segmo.render").render.save_animation(
        np.load(w["nan_motion"]), w["tmp"] / "x.gif"), SegmoError, "NaN",
        "`save_animation` of a NaN motion"),
]


# ------------------------------------------------------------------------------- fixtures


def _corrupt_files(tmp: Path, bundle: Path) -> dict[str, Path]:
    """Every corrupt input the cases name, written once."""
    import shutil

    from safetensors.torch import load_file, save_file

    features = np.load(REPO.parent / "shared" / "fixtures" / "humanml3d" / "012314_features.npy") \
        if (REPO.parent / "shared" / "fixtures").is_dir() else \
        np.zeros((170, 263), dtype=np.float32)
    files = {"motion": tmp / "motion.npy", "file": tmp / "notes.txt"}
    np.save(files["motion"], features[:48])
    files["file"].write_text("not a motion\n")
    files["text_file"] = files["file"]
    files["map_link"] = tmp / "map.png"  # `segmo ground --out` at a link to the user's notes
    files["map_link"].symlink_to("notes.txt")
    files["old_map"] = tmp / "old.png"
    files["old_map"].write_bytes(b"a map of the user's")
    arrays = {"nan_motion": features[:48].copy(), "huge_motion": features[:48] * 1e30,
              "joints": np.zeros((48, 22, 3), np.float32), "wrong_dim": features[:, :100],
              "short_motion": features[:2], "long_motion": np.concatenate([features] * 2),
              "empty_motion": features[:0], "strings": np.array([["a"] * 263] * 8)}
    arrays["nan_motion"][5, 3] = np.nan
    for name, array in arrays.items():
        files[name] = tmp / f"{name}.npy"
        np.save(files[name], array)
    files["npz"] = tmp / "archive.npy"  # np.savez writes a zip whatever the name
    with open(files["npz"], "wb") as handle:
        np.savez(handle, motion=features[:48])
    files["pickle"] = tmp / "pickle.npy"
    np.save(files["pickle"], np.array([{"a": 1}], dtype=object), allow_pickle=True)
    files["foreign"] = tmp / "foreign"
    files["foreign"].mkdir()
    (files["foreign"] / "thesis.tex").write_text("mine")
    files["theirs"] = tmp / "theirs"
    files["theirs"].mkdir()
    (files["theirs"] / "prompts.json").write_text('{"my": "prompts"}')
    files["notes"] = tmp / "notes"  # a folder of the user's holding a file named as an output
    files["notes"].mkdir()
    (files["notes"] / "sample_00.bvh").write_text("my notes")
    files["bad_metrics"] = tmp / "metrics.json"
    files["bad_metrics"].write_text("{oops")
    files["odd_metrics"] = tmp / "odd" / "metrics.json"
    files["odd_metrics"].parent.mkdir()
    files["odd_metrics"].write_text('{"generation": "oops", "config": 5}')
    files["gif_dir"] = tmp / "shown.gif"
    files["gif_dir"].mkdir()
    files["row_metrics"] = tmp / "rows" / "metrics.json"
    files["row_metrics"].parent.mkdir()
    files["row_metrics"].write_text('{"generation": {"generated": {"fid": {"avg": 1}}}}')
    files["empty_metrics"] = tmp / "empty" / "metrics.json"
    files["empty_metrics"].parent.mkdir()
    files["empty_metrics"].write_text("{}")
    files["junk_ckpt"] = tmp / "junk.ckpt"
    files["junk_ckpt"].write_bytes(b"not a checkpoint")
    files["list_ckpt"] = tmp / "list.ckpt"
    torch.save([1, 2, 3], files["list_ckpt"])

    def variant(name: str, edit) -> None:
        files[name] = tmp / name
        shutil.copytree(bundle, files[name])
        edit(files[name])

    def edit_json(path: Path, change) -> None:
        payload = json.loads(path.read_text())
        change(payload)
        path.write_text(json.dumps(payload))

    variant("bad_bundle_json", lambda d: (d / "segmo.json").write_text('{"format": 1,\n'))
    variant("deep_bundle_json", lambda d: (d / "segmo.json").write_text("[" * 200_000))
    variant("bad_format", lambda d: edit_json(d / "segmo.json", lambda p: p.update(format=99)))
    variant("newer_stage", lambda d: edit_json(d / "mask" / "config.json",
                                               lambda p: p.update(format=2, segmo_version="9.0")))
    variant("bad_guidance", lambda d: edit_json(d / "segmo.json",
                                                lambda p: p.update(guidance_scale="high")))
    variant("bad_steps", lambda d: edit_json(d / "segmo.json", lambda p: p.update(steps=0)))
    variant("bad_fps", lambda d: edit_json(d / "segmo.json", lambda p: p.update(fps="fast")))
    variant("bad_text_segmenter", lambda d: edit_json(d / "segmo.json",
                                                      lambda p: p.update(text_segmenter="llama")))
    variant("bad_motion_segmenter", lambda d: edit_json(d / "segmo.json",
                                                        lambda p: p.update(motion_segmenter=42)))
    variant("no_text_encoder", lambda d: edit_json(d / "segmo.json",
                                                   lambda p: p.pop("text_encoder")))
    variant("skeleton_list", lambda d: edit_json(d / "segmo.json",
                                                 lambda p: p.update(skeleton=["t2m"])))
    variant("kind_list", lambda d: edit_json(d / "mask" / "config.json",
                                             lambda p: p.update(kind=["mask"])))
    variant("meta_string", lambda d: edit_json(d / "mask" / "config.json",
                                               lambda p: p.update(meta="x")))
    variant("bad_config_json", lambda d: (d / "mask" / "config.json").write_text("{kind"))
    variant("extra_field", lambda d: edit_json(d / "mask" / "config.json",
                                               lambda p: p["config"].update(wings=2)))
    variant("bad_type", lambda d: edit_json(d / "mask" / "config.json",
                                            lambda p: p["config"].update(dim="big")))
    variant("bad_shape", lambda d: edit_json(d / "mask" / "config.json",
                                             lambda p: p["config"].update(dim=64)))
    variant("huge_config", lambda d: edit_json(d / "mask" / "config.json",  # 2^43 floats a layer
                                               lambda p: p["config"].update(dim=2**20, ff_dim=2**22)))
    variant("bad_weights", lambda d: (d / "mask" / "model.safetensors").write_bytes(b"\0" * 64))

    def poison(d: Path) -> None:
        path = d / "mask" / "model.safetensors"
        state = load_file(str(path))
        state[next(iter(state))].fill_(float("nan"))
        save_file(state, str(path))

    variant("nan_weights", poison)
    variant("no_mask", lambda d: shutil.rmtree(d / "mask"))
    variant("no_residual", lambda d: shutil.rmtree(d / "residual"))

    def residual_loop(d: Path) -> None:
        shutil.rmtree(d / "residual")
        (d / "residual").symlink_to("residual")  # a link to itself

    variant("residual_loop", residual_loop)
    return files


@pytest.fixture(scope="module")
def world(tmp_path_factory, tokenizer_dir) -> dict[str, Path]:
    from segmo.synth.corpus import build_corpus

    root = tmp_path_factory.mktemp("hostile")
    dirs = build_stages(root / "stages", tokenizer_dir["t2m"])
    bundle = SegMo.from_stages(dirs["tokenizer"], dirs["mask"], dirs["residual"], dirs["length"],
                               text_encoder=hash_encoder("hash", TEXT_DIM))
    bundle.save_pretrained(root / "bundle")
    corpus = build_corpus(root / "corpus", 6, seed=0, progress=False)
    (corpus / "text_features").mkdir()  # something a rebuild of the corpus would delete
    tmp = root / "tmp"
    tmp.mkdir()
    cwd = root / "cwd"  # the current folder while a case runs, holding a file of the user's
    cwd.mkdir()
    (cwd / "notes.txt").write_text("mine")
    return {"bundle": root / "bundle", "corpus": corpus, "tmp": tmp, "cwd": cwd, "empty": "",
            "huge": "9" * 5000,
            **_corrupt_files(tmp, root / "bundle")}


@pytest.fixture(autouse=True)
def hash_text_encoder(monkeypatch):
    import segmo.text.encoders

    monkeypatch.setattr(segmo.text.encoders, "get_text_encoder",
                        lambda name, device="cpu": hash_encoder(name, TEXT_DIM))


@pytest.fixture(scope="module")
def model(world) -> SegMo:
    return SegMo.from_pretrained(world["bundle"], text_encoder=hash_encoder("hash", TEXT_DIM))


# ---------------------------------------------------------------------------------- tests


def _argv(case: Cli, world: dict[str, Path]) -> list[str]:
    filled = re.sub(r"\{(\w+)\}", lambda m: str(world[m.group(1)]), case.argv)
    filled = filled.replace("configs/", f"{REPO / 'configs'}/")
    # "a-person-walks" keeps a multi-word prompt one token of the case string.
    return [part.replace("a-person-walks", "a person walks") for part in filled.split(" ")]


@pytest.mark.parametrize("case", CLI_CASES, ids=lambda c: c.id)
def test_cli_refuses_with_one_line(case: Cli, world, capsys, monkeypatch):
    argv = _argv(case, world)
    if case.id == "generate-empty-text":
        argv.append("")
    monkeypatch.chdir(world["cwd"])
    before = sorted(p.name for p in world["tmp"].iterdir())
    line = cli_failure(argv, capsys)
    MESSAGES[case.id] = line.replace(str(world["tmp"].parent), "…")
    assert line.startswith(f"segmo {case.command}: ") or case.id == "unknown-command", line
    assert case.names in line, line
    assert len(line) < 600, "one line, not a dump"
    # Nothing the user had is gone, and a refused command leaves no half-written output.
    assert sorted(p.name for p in world["tmp"].iterdir()) == before
    assert [p.name for p in world["cwd"].iterdir()] == ["notes.txt"]
    assert (world["foreign"] / "thesis.tex").exists() and (world["corpus"] / "text_features").exists()


@pytest.mark.parametrize("case", API_CASES, ids=lambda c: c.id)
def test_api_raises_a_clear_error(case: Api, model, world):
    with pytest.raises(case.error) as info:
        case.call(model, world)
    message = str(info.value)
    MESSAGES[case.id] = f"{type(info.value).__name__}: {message}".replace(
        str(world["tmp"].parent), "…")
    assert case.names in message and "\n" not in message, message
    assert len(message) < 600, "one line, not a dump"


# Hostile-input tests that live beside the code they exercise; the table names them too.
OTHER_MODULES = {"tests/test_text_hostile.py": "segment-texts, encode-texts",
                 "tests/test_training_cli.py": "fit (YAML and arguments)"}


def test_the_documented_table_lists_every_case():
    text = TABLE.read_text(encoding="utf-8")
    documented = set(re.findall(r"^\| `([a-z0-9-]+)` \|", text, flags=re.MULTILINE))
    assert documented == {c.id for c in CLI_CASES} | {c.id for c in API_CASES}
    for module in OTHER_MODULES:
        for name in _hostile_tests(module):
            assert f"`{name}`" in text, f"{module}::{name} is missing from {TABLE.name}"


def _hostile_tests(module: str) -> list[str]:
    """The hostile-input test functions of `module` (with their parametrized case names)."""
    source = (REPO / module).read_text(encoding="utf-8")
    if module.endswith("test_training_cli.py"):
        return [f"fit: {name}" for name in re.findall(r'^    "([^"]+)": \(', source, re.M)]
    return re.findall(r"^def (test_\w+)", source, re.M)


def test_there_are_enough_cases_across_every_command():
    commands = {c.command for c in CLI_CASES}
    assert len(CLI_CASES) + len(API_CASES) >= 60
    assert {"generate", "ground", "bundle", "render", "synth", "evaluate", "demo", "export", "fit",
            "validate", "test"} <= commands


def test_debug_shows_the_traceback(world, capsys):
    from segmo.cli import main

    with pytest.raises(SegmoError):
        main(["--debug", *_argv(CLI_CASES[3], world)])


@pytest.fixture(scope="module", autouse=True)
def write_table():
    yield
    target = os.environ.get("SEGMO_HOSTILE_TABLE")
    if target:
        Path(target).write_text(HEADER + table() + "\n", encoding="utf-8")


HEADER = """# Hostile inputs

What each command and the notebook API do with input nobody should give them. Every case
is a test in `tests/test_hostile_inputs.py`: a command exits with status 2 and prints one
line (`segmo --debug COMMAND ...` shows the traceback instead), an API call raises the
error named; nothing the user had is lost and nothing half-written is left. The last
column is the line printed in the run that wrote this table (`…` is the test's scratch
folder).

"""


def table() -> str:
    rows = ["| case | command | hostile input | what it does now |", "| --- | --- | --- | --- |"]
    for c in CLI_CASES:
        rows.append(f"| `{c.id}` | `segmo {c.command}` | {c.what} | "
                    f"{_cell(MESSAGES.get(c.id, c.names))} |")
    for c in API_CASES:
        rows.append(f"| `{c.id}` | notebook API | {c.what} | "
                    f"{_cell(MESSAGES.get(c.id, c.error.__name__ + ': ' + c.names))} |")
    for module, commands in OTHER_MODULES.items():
        rows += ["", f"More cases of {commands}, in `{module}` (each asserts exit status 2, one "
                 "line naming the file or argument, no traceback):", ""]
        rows += [f"- `{name}`" for name in _hostile_tests(module)]
    return "\n".join(rows)


def _cell(text: str) -> str:
    return "`" + text.replace("|", "\\|").replace("`", "'") + "`"


def test_ctrl_c_while_a_command_loads_is_one_line(monkeypatch, capsys):
    """Ctrl-C in the seconds torch takes to import printed a 58-line KeyboardInterrupt
    traceback: the command's module was imported before the handler was in place."""
    import importlib

    from segmo.cli import main

    def interrupted(name, *args):
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib, "import_module", interrupted)
    with pytest.raises(SystemExit) as exit_:
        main(["synth", "--out", "nowhere"])
    assert exit_.value.code == 130
    assert capsys.readouterr().err == "segmo synth: interrupted\n"
