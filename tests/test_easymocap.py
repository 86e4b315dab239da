"""Dataset `easymocap` and the converter: a capture written by these tests in EasyMocap's layout (YAML through cv2's
FileStorage, JSON parameters) and the same capture in the ZJU-MoCap layout must give identical samples through the
EasyMocap reader, the ZJU reader and the converter; EasyMocap's own file quirks; SMPL-X poses with hand PCA posed
against smplx's own forward; one test per kind of bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_zju_format import ring_cameras

from framework.data.easymocap_layout import EasyMocapError, EasyMocapSequence, read_easymocap_cameras
from framework.data.zju.dataset import ZjuMocapDataset
from framework.data.zju.writer import ZjuWriter
from framework.errors import SplatrigError
from framework.geometry import axis_angle_to_rotmat
from plugins.body.procedural import ProceduralBody
from plugins.dataset.easymocap import EasyMocapDataset

NAMES = ["01", "02", "03", "04"]


@dataclass
class Capture:
    """A posed body seen by a calibrated ring: K in splatrig's pixel convention, T in metres, distorted images."""

    names: list[str]
    K: np.ndarray  # [C, 3, 3]
    D: np.ndarray  # [C, 5]
    R: np.ndarray  # [C, 3, 3]
    T: np.ndarray  # [C, 3] metres
    images: np.ndarray  # [F, C, H, W, 3] uint8, as captured (distorted)
    masks: np.ndarray  # [F, C, H, W] uint8 {0, 1}
    params: list[dict]  # poses [1, J*3], Rh [1, 3], Th [1, 3], shapes [1, 10]
    vertices: np.ndarray  # [F, V, 3] world

    @property
    def K_opencv(self) -> np.ndarray:
        K = self.K.copy()
        K[:, :2, 2] -= 0.5
        return K


@pytest.fixture(scope="module")
def body() -> ProceduralBody:
    return ProceduralBody(segments=8)


def make_capture(
    body: ProceduralBody, C: int = 4, F: int = 3, size: int = 64, distortion: bool = True, seed: int = 0
) -> Capture:
    """Masks are the posed mesh's triangles projected with OpenCV's distortion model, so after undistortion they
    match the pinhole projection of the vertices; images are a per-camera colour ramp inside the mask."""
    g = torch.Generator().manual_seed(seed)
    K, R, T = ring_cameras(C, radius=3.5, size=size, f=0.8 * size, seed=seed)
    D = np.zeros((C, 5))
    if distortion:
        D[:, 0], D[:, 1], D[:, 2] = np.linspace(-0.08, 0.06, C), 0.01, 0.001
    Kcv = K.copy()
    Kcv[:, :2, 2] -= 0.5
    faces = body.faces.numpy()
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    images = np.zeros((F, C, size, size, 3), np.uint8)
    masks = np.zeros((F, C, size, size), np.uint8)
    params, verts = [], []
    for f in range(F):
        pose = torch.randn(1, body.num_joints, 3, generator=g) * 0.25
        Rh = torch.randn(1, 3, generator=g) * 0.3
        Th = torch.randn(1, 3, generator=g) * 0.1
        local = body.posed_vertices(pose)[0].double()
        X = (local @ axis_angle_to_rotmat(Rh.double())[0].T + Th.double()).numpy()  # world = R(Rh) M + Th
        for c in range(C):
            uv = cv2.projectPoints(X, cv2.Rodrigues(R[c])[0], T[c], Kcv[c], D[c])[0][:, 0]  # OpenCV pixel centres
            cv2.fillPoly(masks[f, c], list(np.round(uv[faces] * 16).astype(np.int32)), 1, cv2.LINE_8, shift=4)
            ramp = np.stack([40 + 2 * jj, 60 + 2 * ii, np.full_like(jj, 50 * c)], -1) % 256
            images[f, c][masks[f, c] > 0] = ramp[masks[f, c] > 0]
        params.append(
            {
                "poses": pose.numpy().reshape(1, -1),
                "Rh": Rh.numpy(),
                "Th": Th.numpy(),
                "shapes": (torch.randn(1, 10, generator=g) * 0.5).numpy(),
            }
        )
        verts.append(X.astype(np.float32))
    return Capture(
        NAMES[:C] if C <= 4 else [f"{c + 1:02d}" for c in range(C)], K, D, R, T, images, masks, params, np.stack(verts)
    )


def write_calibration(
    root: Path,
    names: list[str],
    K_cv: np.ndarray,
    D: np.ndarray,
    R: np.ndarray,
    T: np.ndarray,
    size: tuple[int, int] | None = None,
    Rot: np.ndarray | None = None,
) -> None:
    """intri.yml / extri.yml through cv2.FileStorage, with the keys EasyMocap's write_camera writes (Rot_: `Rot`, R
    by default)."""
    Rot = R if Rot is None else Rot
    root.mkdir(parents=True, exist_ok=True)
    for fname in ("intri.yml", "extri.yml"):
        fs = cv2.FileStorage(str(root / fname), cv2.FILE_STORAGE_WRITE)
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        for n in names:
            fs.write("", n)
        fs.endWriteStruct()
        for c, n in enumerate(names):
            if fname == "intri.yml":
                fs.write(f"K_{n}", K_cv[c])
                fs.write(f"dist_{n}", D[c].reshape(1, 5))
                if size is not None:
                    fs.write(f"H_{n}", size[1])
                    fs.write(f"W_{n}", size[0])
            else:
                fs.write(f"R_{n}", cv2.Rodrigues(R[c])[0])
                fs.write(f"Rot_{n}", Rot[c])
                fs.write(f"T_{n}", T[c].reshape(3, 1))
        fs.release()


def write_json(path: Path, people: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps([{k: (np.asarray(v).tolist() if k != "id" else v) for k, v in p.items()} for p in people], indent=4)
    )


def write_easymocap(
    root: Path,
    cap: Capture,
    mask_folder: str = "mask-schp",
    first: int = 100,
    output: str = "output-smpl-3d",
    extra_people: bool = False,
    fits_by_image_name: bool = False,
) -> Path:
    """The capture as EasyMocap leaves it; image names start at `first`, fits are named by the frame's position as
    mv1p.py names them (or by the image name). Masks are written as SCHP-style colour labels (foreground colours with a
    zero red channel included); parameters as mv1p.py writes them (2-D lists)."""
    F, C, H, W = cap.masks.shape
    write_calibration(root, cap.names, cap.K_opencv, cap.D, cap.R, cap.T, size=(W, H))
    labels = np.array([[0, 0, 0], [0, 0, 85], [0, 128, 0], [128, 0, 128]], np.uint8)  # BGR; background 0
    for f in range(F):
        stem = f"{first + f:06d}"
        for c, n in enumerate(cap.names):
            (root / "images" / n).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / "images" / n / f"{stem}.png"), cap.images[f, c][..., ::-1])
            part = cap.masks[f, c] * (1 + (np.arange(W)[None, :] * 3 // W))  # three "parts" left to right
            (root / mask_folder / n).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / mask_folder / n / f"{stem}.png"), labels[np.clip(part, 0, 3)])
        p = {"id": 0, **{k: np.asarray(v).reshape(1, -1) for k, v in cap.params[f].items()}}
        people = [p] + ([{**p, "id": 3, "Th": p["Th"] + 1.0}] if extra_people else [])
        fit = stem if fits_by_image_name else f"{f:06d}"
        write_json(root / output / "smpl" / f"{fit}.json", people)
        write_json(
            root / output / "vertices" / f"{fit}.json",
            [{"id": 0, "vertices": cap.vertices[f]}]
            + ([{"id": 3, "vertices": cap.vertices[f] + 1.0}] if extra_people else []),
        )
    return root


def write_zju(root: Path, cap: Capture, body_name: str = "procedural") -> Path:
    w = ZjuWriter(root, cap.names, image_ext=".png")
    w.write_cameras(cap.K, cap.D, cap.R, cap.T)
    for f in range(len(cap.params)):
        w.write_frame(f, cap.images[f], cap.masks[f], {**cap.params[f], "body": body_name}, cap.vertices[f])
    w.finish()
    return root


@pytest.fixture(scope="module")
def capture(body: ProceduralBody, tmp_path_factory) -> tuple[Capture, Path, Path]:
    base = tmp_path_factory.mktemp("capture")
    cap = make_capture(body)
    return cap, write_easymocap(base / "easymocap", cap), write_zju(base / "zju", cap)


def assert_same_samples(a, b, cams_atol: float = 1e-6) -> None:
    assert len(a) == len(b) and a.frame_ids == b.frame_ids and a.views == b.views
    assert a.num_frames_total == b.num_frames_total and a.body_name == b.body_name
    torch.testing.assert_close(a.cameras.K, b.cameras.K, rtol=0, atol=cams_atol)
    torch.testing.assert_close(a.cameras.world_to_cam, b.cameras.world_to_cam, rtol=0, atol=cams_atol)
    torch.testing.assert_close(a.poses(), b.poses(), rtol=0, atol=1e-6)
    torch.testing.assert_close(a.roots(), b.roots(), rtol=0, atol=1e-6)
    torch.testing.assert_close(a.bounds, b.bounds, rtol=0, atol=1e-5)
    torch.testing.assert_close(a.fitted_betas(), b.fitted_betas())
    for i in range(len(a)):
        x, y = a[i], b[i]
        for key in ("image", "mask", "boundary", "frame", "view", "pose", "root", "betas"):
            torch.testing.assert_close(getattr(x, key), getattr(y, key), rtol=0, atol=1e-6, msg=f"{key} of item {i}")


# ------------------------------------------------------------------------------------------------ agreement
@pytest.mark.parametrize("split", ["train", "novel_view"])
def test_reader_converter_and_zju_reader_agree(capture, tmp_path: Path, split: str) -> None:
    cap, em_root, zju_root = capture
    em = EasyMocapDataset(str(em_root), split=split, test_views=["02"], body="procedural", boundary_px=2)
    assert em.train_views == [0, 2, 3] and em.test_views == [1]  # names -> indices; train = the other cameras
    assert em.mask_source == "mask-schp" and em.seq.stems[0] == "000100"
    zju = ZjuMocapDataset(
        str(zju_root), split=split, protocol=None, train_views=[0, 2, 3], test_views=[1], boundary_px=2
    )
    assert_same_samples(em, zju)
    out = tmp_path / "converted"
    cmd = [sys.executable, "-m", "framework.data.convert", f"root={em_root}", f"out={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "wrote" in proc.stdout, proc.stderr[-2000:]
    conv = ZjuMocapDataset(
        str(out), split=split, protocol=None, train_views=[0, 2, 3], test_views=[1], boundary_px=2, body="procedural"
    )
    assert_same_samples(em, conv)
    source = json.loads((out / "easymocap_source.json").read_text())
    assert source["frames"] == ["000100", "000101", "000102"] and source["mask_dir"] == "mask-schp"
    # images were copied, not re-encoded
    assert (out / "01" / "000002.png").read_bytes() == (em_root / "images" / "01" / "000102.png").read_bytes()


def test_samples_reproject_the_stored_vertices(capture) -> None:
    """Independent of the ZJU reader: undistorted masks contain the pinhole projections of the stored vertices, and
    the parameters pose the body onto them with EasyMocap's root convention world = R(Rh) M(poses) + Th."""
    cap, em_root, _ = capture
    em = EasyMocapDataset(str(em_root), body="procedural", boundary_px=2)
    body = ProceduralBody(segments=8)
    inside = total = 0
    for i in range(len(em)):
        b = em[i]
        f = int(b.frame[0])
        world = body.posed_vertices(b.pose)[0] @ b.root[0, :3, :3].T + b.root[0, :3, 3]
        np.testing.assert_allclose(world.numpy(), cap.vertices[f], atol=2e-5)
        X = torch.from_numpy(cap.vertices[f]).double()
        w2c = b.cameras.world_to_cam[0].double()
        p = (X @ w2c[:3, :3].T + w2c[:3, 3]) @ b.cameras.K[0].double().T
        uv = (p[:, :2] / p[:, 2:3]).floor().long().clamp(0, 63)
        inside += int((b.mask[0, uv[:, 1], uv[:, 0]] > 0.5).sum())
        total += len(uv)
    assert inside / total > 0.97, inside / total


# ------------------------------------------------------------------------------------------------ EasyMocap's files
def test_easymocap_own_yaml_text_is_read(tmp_path: Path) -> None:
    """The text EasyMocap's FileStorage writer produces ("%YAML:1.0", CRLF, `dt: d`, quoted names), with R_ as a
    Rodrigues vector only, no dist and a numeric camera name written unquoted."""
    K, R, T = ring_cameras(2, size=32)
    rvecs = [cv2.Rodrigues(r)[0] for r in R]

    def mat(key, a):
        a = np.atleast_2d(a)
        rows, cols = a.shape
        data = ", ".join(f"{x:.6f}" for x in a.ravel())
        return [f"{key}: !!opencv-matrix", f"  rows: {rows}", f"  cols: {cols}", "  dt: d", f"  data: [{data}]"]

    head = ["%YAML:1.0", "---", "names:", '  - "cam_a"', "  - 7"]
    intri = head + mat("K_cam_a", K[0]) + mat("K_7", K[1]) + mat("dist_cam_a", np.zeros((1, 5)))
    extri = head + mat("R_cam_a", rvecs[0]) + mat("T_cam_a", T[0][:, None]) + mat("R_7", rvecs[1])
    extri += mat("T_7", T[1][:, None])
    (tmp_path / "intri.yml").write_bytes("\r\n".join(intri).encode() + b"\r\n")
    (tmp_path / "extri.yml").write_bytes("\r\n".join(extri).encode() + b"\r\n")
    names, cams, sizes = read_easymocap_cameras(tmp_path)
    assert names == ["cam_a", "7"] and sizes == [None, None]
    np.testing.assert_allclose(cams.R, R, atol=1e-5)  # 6 decimals of the Rodrigues vector
    np.testing.assert_allclose(cams.T_m, T, atol=1e-6)
    np.testing.assert_allclose(cams.K, K, atol=1e-6)
    assert not cams.D.any()


def test_frames_like_easymocap_shortest_camera_and_fit_names(body: ProceduralBody, tmp_path: Path, capsys) -> None:
    """Frame i is the i-th image of every camera; a camera with extra trailing frames is cut, as EasyMocap's MVBase
    does; fits are found by position (mv1p.py) or by image name."""
    cap = make_capture(body, C=2, F=3, size=32, distortion=False, seed=6)
    root = write_easymocap(tmp_path / "cap", cap, fits_by_image_name=True)
    extra = root / "images" / "01" / "000103.png"
    extra.write_bytes((root / "images" / "01" / "000100.png").read_bytes())
    seq = EasyMocapSequence(root)
    assert seq.num_frames == 3 and seq.stems == ["000100", "000101", "000102"]
    assert "using the first 3 frames of every camera" in capsys.readouterr().err
    assert seq.params_path(2).name == "000102.json"  # fits named by image name
    ds = EasyMocapDataset(str(root), body="procedural")
    torch.testing.assert_close(ds.roots()[2, :3, 3], torch.tensor(cap.params[2]["Th"][0], dtype=torch.float32))
    by_position = write_easymocap(tmp_path / "pos", cap)
    assert EasyMocapSequence(by_position).params_path(2).name == "000002.json"


def test_mask_folder_choice_and_people(body: ProceduralBody, tmp_path: Path) -> None:
    cap = make_capture(body, C=2, F=2, size=32, distortion=False, seed=3)
    root = write_easymocap(tmp_path / "cap", cap, mask_folder="mask", extra_people=True)
    with pytest.raises(EasyMocapError, match=r"holds 2 people \(ids \[0, 3\]\); choose one with data.person_id"):
        EasyMocapDataset(str(root), body="procedural")
    ds = EasyMocapDataset(str(root), body="procedural", person_id=3)
    torch.testing.assert_close(ds.roots()[:, :3, 3], torch.tensor(np.concatenate([p["Th"] for p in cap.params]) + 1))
    assert ds.mask_source == "mask"
    # both folders: mask/ wins unless data.mask_dir says otherwise
    write_easymocap(root, cap, mask_folder="mask-schp")
    assert EasyMocapSequence(root, person_id=0).mask_dir == "mask"
    assert EasyMocapSequence(root, person_id=0, mask_dir="mask-schp").mask_dir == "mask-schp"
    # SCHP colour labels with a zero red channel are foreground too
    seq = EasyMocapSequence(root, person_id=0, mask_dir="mask-schp")
    np.testing.assert_array_equal(seq.mask(1, 1), cap.masks[1, 1])


def test_smplx_hand_pca_poses_pose_like_smplx(tmp_path: Path) -> None:
    """87-value SMPL-X poses (EasyMocap: body 66, 6 + 6 hand PCA, jaw and eyes 9) come out as the 165-value skeleton
    pose; posed by `body=smplx` with world = R(Rh) M + Th they equal smplx's own PCA-hand forward."""
    pytest.importorskip("smplx")
    from test_body_smplx import smplx_forward, write_smplx_file

    from plugins.body.smplx_body import SMPLXBody

    model = tmp_path / "models" / "SMPLX_NEUTRAL.npz"
    write_smplx_file(model)
    rng = np.random.default_rng(5)
    K, R, T = ring_cameras(2, size=16)
    write_calibration(tmp_path / "cap", ["a", "b"], K, np.zeros((2, 5)), R, T)
    poses87 = 0.3 * rng.standard_normal((2, 87))
    poses87[:, :3] = 0  # EasyMocap keeps the root slot at zero and carries it in Rh
    Rh, Th = 0.5 * rng.standard_normal((2, 3)), rng.standard_normal((2, 3))
    for f in range(2):
        for n in ("a", "b"):
            for folder in ("images", "mask"):
                (tmp_path / "cap" / folder / n).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(tmp_path / "cap" / folder / n / f"{f:06d}.png"), np.full((16, 16), 255, np.uint8))
        write_json(
            tmp_path / "cap" / "output" / "smpl" / f"{f:06d}.json",
            [
                {
                    "id": 0,
                    "Rh": Rh[f][None],
                    "Th": Th[f][None],
                    "poses": poses87[f][None],
                    "shapes": np.zeros((1, 10)),
                    "expression": np.zeros((1, 10)),
                }
            ],
        )
    with pytest.raises(EasyMocapError, match="87 values.*body.model_path=/path/to/SMPLX_<GENDER>.pkl"):
        EasyMocapDataset(str(tmp_path / "cap"))
    ds = EasyMocapDataset(str(tmp_path / "cap"), body_model_path=str(model.parent))
    assert ds.body_name == "smplx" and ds.poses().shape == (2, 55, 3)
    body = SMPLXBody(model_path=str(model))
    for f in range(2):
        b = ds[f * 2]
        ours = body.posed_vertices(b.pose.double())[0] @ b.root[0, :3, :3].double().T + b.root[0, :3, 3].double()
        p = torch.from_numpy(poses87[f : f + 1])
        full = torch.zeros(1, 55, 3, dtype=torch.float64)
        full[0, :22] = p[0, :66].reshape(22, 3)
        full[0, 22:25] = p[0, 78:87].reshape(3, 3)
        ref = smplx_forward(
            model,
            full,
            torch.zeros(1, 10, dtype=torch.float64),
            left_hand_pose=p[:, 66:72],
            right_hand_pose=p[:, 72:78],
        )[0]
        ref = ref @ torch.from_numpy(cv2.Rodrigues(Rh[f])[0]).T + torch.from_numpy(Th[f])
        assert (ours - ref).abs().max() < 1e-5


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_missing_calibration(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"intri\.yml is missing: expected EasyMocap's calibration") as e:
        EasyMocapDataset(str(tmp_path / "nowhere"))
    assert isinstance(e.value, SplatrigError) and "does not exist" in str(e.value)


def test_bad_rotation_pair_and_camera_folders(body: ProceduralBody, tmp_path: Path) -> None:
    cap = make_capture(body, C=2, F=2, size=32, distortion=False, seed=4)
    root = write_easymocap(tmp_path / "cap", cap)
    Rbad = cap.R.copy()
    Rbad[1] = Rbad[1] @ cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]
    write_calibration(root, cap.names, cap.K_opencv, cap.D, cap.R, cap.T, Rot=Rbad)
    with pytest.raises(EasyMocapError, match=r"R_02 \(Rodrigues\) and Rot_02 describe different rotations"):
        EasyMocapDataset(str(root), body="procedural")
    write_easymocap(root, cap)
    (root / "images" / "02" / "000100.png").rename(root / "images" / "02" / "000099.png")
    with pytest.raises(
        EasyMocapError,
        match=r"images/02: frame 0 is 000099 but in .*images/01 it is 000100; the "
        r"cameras are out of step",
    ):
        EasyMocapDataset(str(root), body="procedural")
    (root / "images" / "02" / "000099.png").unlink()
    with pytest.raises(EasyMocapError, match=r"frame 0 is 000101 but .* it is 000100"):
        EasyMocapDataset(str(root), body="procedural")
    import shutil

    shutil.rmtree(root / "images" / "02")
    with pytest.raises(FileNotFoundError, match=r"intri\.yml names camera '02' but there is no image folder"):
        EasyMocapDataset(str(root), body="procedural")
    ds = EasyMocapDataset(str(root), body="procedural", cameras=["01"])  # the cameras that remain
    assert ds.cameras.num == 1 and len(ds) == 2


def test_bad_params_folders_and_pose_lengths(body: ProceduralBody, tmp_path: Path) -> None:
    cap = make_capture(body, C=2, F=2, size=32, distortion=False, seed=5)
    root = write_easymocap(tmp_path / "cap", cap)
    write_json(root / "output" / "smplx" / "smpl" / "000000.json", [{"id": 0}])
    with pytest.raises(
        EasyMocapError,
        match=r"several parameter folders \['output/smplx/smpl', "
        r"'output-smpl-3d/smpl'\]; choose one with data.params_dir=",
    ):
        EasyMocapDataset(str(root))
    with pytest.raises(EasyMocapError, match=r"000000\.json: expected keys Rh, Th, poses .* missing \['Rh', 'Th'"):
        EasyMocapDataset(str(root), params_dir="output/smplx/smpl")
    ok = EasyMocapDataset(str(root), params_dir="output-smpl-3d/smpl", body="procedural")
    assert ok.body_name == "procedural"
    write_json(
        root / "output" / "smplx" / "smpl" / "000000.json",
        [{"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0, 0]], "poses": [[0.0] * 78]}],
    )
    with pytest.raises(EasyMocapError, match=r"78 values \(SMPL\+H with hand PCA\), which splatrig does not read"):
        EasyMocapDataset(str(root), params_dir="output/smplx/smpl")
    (root / "output-smpl-3d" / "smpl" / "000001.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"params of frame 1 is missing: expected .*000001\.json"):
        EasyMocapDataset(str(root), params_dir="output-smpl-3d/smpl", body="procedural")
