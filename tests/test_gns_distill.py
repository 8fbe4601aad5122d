"""Training against a teacher (train.teacher, gns.distill) and graphs rebuilt for a model of the
other kind (gns.graph.with_surface_edges)."""
import pytest
import torch
from gns_fixtures import write_toss_dataset

from datagen.shards import Dataset
from gns.checkpoint import CheckpointError, load_model
from gns.config import ConfigError
from gns.data import ObjectTracks
from gns.distill import Teacher
from gns.graph import MeshLibrary, with_surface_edges
from gns.rigid import shape_match_packed
from gns.train import read_checkpoint, train, unrolled_loss
from test_gns_train import quiet, tiny

CENTRE = "features.centre_node=true"
SPOKES = "features.surface_edges=false"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_toss_dataset(tmp_path_factory.mktemp("toss"), train=4, valid=0, frames=10)


@pytest.fixture(scope="module")
def teacher_run(data, tmp_path_factory):
    """A full-graph model (surface edges and spokes), trained a little."""
    run = tmp_path_factory.mktemp("teacher") / "run"
    train(data, run, tiny("train.steps=20", "train.lr_init=1e-3", CENTRE), log=quiet)
    return run


def test_surface_edges_rebuilt_from_faces_are_the_ones_the_library_packs(data):
    meshes = Dataset(data).meshes
    full, spokes = MeshLibrary(meshes, centre_node=True), MeshLibrary(meshes, centre_node=True, surface_edges=False)
    shape = torch.tensor([0, 0, 0, 0])
    size, friction = torch.tensor([0.5, 1.0, 2.0, 0.7]), torch.rand(4)
    f, s = full.pack(shape, size, friction, friction), spokes.pack(shape, size, friction, friction)
    for made, packed in ((with_surface_edges(f, False), s), (with_surface_edges(s, True), f)):
        assert torch.equal(made.mesh_edges.senders, packed.mesh_edges.senders)
        assert torch.equal(made.mesh_edges.receivers, packed.mesh_edges.receivers)
    assert len(f.mesh_edges.senders) > len(s.mesh_edges.senders)


def test_a_teacher_predicts_on_a_spokes_only_students_graphs_what_it_does_on_its_own(data, teacher_run):
    ds = Dataset(data)
    scenes = ds.load("train")
    student = load_model(read_checkpoint(teacher_run / "latest.pt"))[0]   # any model on spokes-only graphs
    student._graph_settings = {**student._graph_settings, "surface_edges": False}
    teacher = Teacher(str(teacher_run), student, torch.device("cpu"), autocast="none")
    windows = torch.tensor([0, 3, 9])
    own = ObjectTracks(scenes, teacher.model.mesh_library(ds.meshes)).batch(windows)
    theirs = ObjectTracks(scenes, student.mesh_library(ds.meshes)).batch(windows)
    assert len(theirs.graph.mesh_edges.senders) < len(own.graph.mesh_edges.senders)
    g = own.graph
    with torch.no_grad():
        x = teacher.model.predict_next(*own.history.unbind(1), g)
    expected = shape_match_packed(x, g.rest, g.node_graph, g.num_graphs)[2]
    got = teacher.next_frame(list(theirs.history.unbind(1)), theirs.graph)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-9)
    # and the loss asks the student for that frame, or for a blend with the truth
    sim = student.eval()
    blended = 0.25 * expected + 0.75 * theirs.target
    torch.testing.assert_close(unrolled_loss(sim, theirs, teacher=teacher, teacher_weight=0.25),
                               sim.loss(theirs.history, blended, theirs.graph), rtol=1e-6, atol=0)


def test_a_student_trained_on_a_teacher_learns_the_teachers_answers_not_the_truths(data, teacher_run, tmp_path):
    over = ("train.steps=60", "train.lr_init=3e-3", CENTRE, SPOKES)
    train(data, tmp_path / "truth", tiny(*over), log=quiet)
    train(data, tmp_path / "taught", tiny(*over, f"train.teacher={teacher_run}"), log=quiet)
    train(data, tmp_path / "weight0", tiny(*over, f"train.teacher={teacher_run}", "train.teacher_weight=0"), log=quiet)
    a, b = (read_checkpoint(tmp_path / n / "latest.pt")["model"] for n in ("truth", "weight0"))
    assert all(torch.equal(a[k], b[k]) for k in a)   # weight 0: the truth's targets, the same run
    ds = Dataset(data)
    truth_model, taught = (load_model(tmp_path / n / "latest.pt")[0] for n in ("truth", "taught"))
    teacher = Teacher(str(teacher_run), taught, torch.device("cpu"), autocast="none")
    batch = ObjectTracks(ds.load("train"), taught.mesh_library(ds.meshes)).batch(torch.arange(20))
    frames = list(batch.history.unbind(1))
    wanted = teacher.next_frame(frames, batch.graph)
    with torch.no_grad():
        off = {name: float((m.predict_next(*frames, batch.graph) - wanted).norm(dim=1).mean())
               for name, m in (("truth", truth_model), ("taught", taught))}
    assert off["taught"] < 0.7 * off["truth"], off


def test_a_full_mesh_teacher_gives_a_coarse_student_its_predicted_pose(data, teacher_run, tmp_path):
    ds = Dataset(data)
    scenes = ds.load("train")
    coarse_cfg = tiny(CENTRE, SPOKES, "features.mesh_vertices=4")
    from gns.checkpoint import build_simulator
    from gns.data import feature_spec
    student = build_simulator(coarse_cfg, feature_spec(ds, scenes)).eval()
    tracks = ObjectTracks(scenes, student.mesh_library(ds.meshes))
    with pytest.raises(CheckpointError, match="no training tracks"):
        Teacher(str(teacher_run), student, torch.device("cpu"), autocast="none")
    teacher = Teacher(str(teacher_run), student, torch.device("cpu"), tracks, ds.meshes, autocast="none")
    windows = torch.tensor([1, 4, 11])
    theirs = tracks.batch(windows)
    own = ObjectTracks(scenes, teacher.model.mesh_library(ds.meshes)).batch(windows)
    assert theirs.graph.num_nodes < own.graph.num_nodes
    g = own.graph
    with torch.no_grad():
        x = teacher.model.predict_next(*own.history.unbind(1), g)
    rot, centre, _ = shape_match_packed(x, g.rest, g.node_graph, g.num_graphs)
    got = teacher.next_frame(list(theirs.history.unbind(1)), theirs.graph, theirs.tracks)
    s = theirs.graph
    torch.testing.assert_close(got, torch.einsum("nij,nj->ni", rot[s.node_graph], s.rest) + centre[s.node_graph],
                               rtol=0, atol=1e-9)
    with pytest.raises(CheckpointError, match="augment.mirror"):
        Teacher(str(teacher_run), student, torch.device("cpu"), tracks, ds.meshes, maps_body_frames=True)
    # and through training, pushforward steps included (the teacher answers the student's own frames)
    train(data, tmp_path / "coarse", tiny("train.steps=3", CENTRE, SPOKES, "features.mesh_vertices=4",
                                          "train.unroll_steps=2", f"train.teacher={teacher_run}"), log=quiet)
    assert read_checkpoint(tmp_path / "coarse" / "latest.pt")["config"]["train"]["teacher"] == str(teacher_run)


def test_a_bad_teacher_is_one_line_before_the_run_folder_exists(data, teacher_run, tmp_path):
    with pytest.raises(CheckpointError, match="train.teacher .*augment.mirror"):
        train(data, tmp_path / "coarse", tiny("train.steps=2", CENTRE, "features.mesh_vertices=4",
                                              "augment.mirror=true", f"train.teacher={teacher_run}"), log=quiet)
    assert not (tmp_path / "coarse").exists()
    with pytest.raises(CheckpointError, match="train.teacher .*nowhere.pt"):
        train(data, tmp_path / "missing", tiny("train.steps=2", CENTRE, f"train.teacher={tmp_path / 'nowhere.pt'}"),
              log=quiet)
    assert not (tmp_path / "missing").exists()
    with pytest.raises(ConfigError, match="train.teacher_weight"):
        tiny("train.teacher_weight=1.5")


def test_a_symmetrized_teacher_answers_what_its_symmetrized_rollout_predicts(data, teacher_run, tmp_path):
    ds = Dataset(data)
    model = load_model(read_checkpoint(teacher_run / "latest.pt"))[0]
    batch = ObjectTracks(ds.load("train"), model.mesh_library(ds.meshes)).batch(torch.tensor([0, 5, 13]))
    frames, g = list(batch.history.unbind(1)), batch.graph
    answers = {}
    for group in ("", "d1", "d2"):
        teacher = Teacher(f"{teacher_run}+{teacher_run}", model, torch.device("cpu"), autocast="none",
                          symmetrize=group)
        answers[group] = teacher.next_frame(frames, g)
        model.symmetrize = group or False
        with torch.no_grad():
            x = model.predict_next(*frames, g)
        torch.testing.assert_close(answers[group], shape_match_packed(x, g.rest, g.node_graph, g.num_graphs)[2],
                                   rtol=0, atol=1e-9)
    # the images change the answer (the network alone is not mirror-equivariant)
    assert float((answers["d2"] - answers[""]).abs().max()) > 1e-7
    assert float((answers["d2"] - answers["d1"]).abs().max()) > 1e-7
    train(data, tmp_path / "run", tiny("train.steps=2", f"train.teacher={teacher_run}", "train.teacher_symmetrize=d1"),
          log=quiet)
    assert read_checkpoint(tmp_path / "run" / "latest.pt")["config"]["train"]["teacher_symmetrize"] == "d1"


def test_teacher_symmetrize_names_a_symmetry_group_and_needs_a_teacher(teacher_run):
    from gns.config import TEACHER_GROUPS
    from gns.symmetry import SYMMETRY_GROUPS
    assert set(TEACHER_GROUPS) == set(SYMMETRY_GROUPS)
    with pytest.raises(ConfigError, match="train.teacher_symmetrize must be"):
        tiny(f"train.teacher={teacher_run}", "train.teacher_symmetrize=d3")
    with pytest.raises(ConfigError, match="train.teacher_symmetrize needs train.teacher"):
        tiny("train.teacher_symmetrize=d2")


def test_a_teacher_may_be_named_as_gns_eval_names_a_shipped_model(teacher_run):
    from gns.checkpoint import SHIPPED_MODELS
    from gns.distill import teacher_paths
    paths = teacher_paths(f"gns_movi_a_low_spokes_chain_avg + {teacher_run}")
    assert paths == [SHIPPED_MODELS / "gns_movi_a_low_spokes_chain_avg.pt", teacher_run / "latest.pt"]
    assert paths[0].is_file()


def test_init_from_may_name_a_shipped_model(data, tmp_path):
    # the shipped MOVi-A model is read (its architecture is named against this one's), not looked for as a path
    with pytest.raises(CheckpointError, match=r"models/gns_movi_a_low_distilled\.pt \(train.init_from\): model.latent_size"):
        train(data, tmp_path / "run", tiny("train.steps=2", "train.init_from=gns_movi_a_low_distilled"), log=quiet)
    assert not (tmp_path / "run").exists()
