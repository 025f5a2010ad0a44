// The viewer page: an InteractAvatar avatar played in 3D with Spark (three.js). index.html loads data/manifest.js
// (window.IAV.manifest, written by the pipeline's viewer stage) and then this bundle.
//
// URL parameters: motion, frame, camera (a capture camera id), scale (canvas pixels per camera pixel).
// window.viewer is the page's handle for scripts and tests: ready (a promise), show({motion, frame, camera}) (a
// promise resolved once that frame is drawn), state, stats ({pose_ms, frame_ms}), draws() (frames drawn so far).

import { PackedSplats, SparkRenderer, SplatMesh, setPackedSplat } from "@sparkjsdev/spark";
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { loadScript, unpack } from "./data.js";
import { poseFrame, usedTriangles } from "./pose.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const manifest = window.IAV.manifest;

const state = { motion: null, frame: 0, camera: null, playing: false, visible: manifest.parts.map(() => true) };
const stats = { pose_ms: null, frame_ms: null };
const poseTimes = [];
const frameIntervals = [];

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted.length ? sorted[Math.floor(sorted.length / 2)] : null;
}

function pad(frame) {
  return String(frame).padStart(5, "0");
}

// A relative URL of path components (names from the manifest: motions, camera ids), each percent-encoded whole so
// that no "#", "?", "/" or "%" in a name changes the URL (data_schemas/web_escape.py's url_path on the Python side).
function urlPath(...components) {
  return components.map(encodeURIComponent).join("/");
}

async function main() {
  // --- the avatar ---------------------------------------------------------------------------------------------

  const avatarEntry = await loadScript(manifest.avatar.file).then(() => window.IAV.avatar);
  const statics = unpack(avatarEntry);
  const N = statics.triangle.length;
  // the quantisation of the vertices and the overrides' steps (avatar/viewer/codec.py's POSITION_LEVELS and STEPS)
  const avatar = {
    statics,
    steps: manifest.steps,
    vertexLevels: manifest.vertex_levels,
    ...usedTriangles(statics.triangle),
  };
  avatar.frames = new Float64Array(17 * avatar.used.length);
  const posed = {
    centers: new Float64Array(3 * N),
    scales: new Float64Array(3 * N),
    quats: new Float64Array(4 * N),
    rgba: new Float64Array(4 * N),
  };
  const motions = Object.create(null); // name -> loaded motion; no prototype, so a motion may be named "constructor"

  async function motionData(name) {
    if (!motions[name]) {
      const meta = manifest.motions.find((m) => m.name === name);
      await loadScript(meta.file);
      const sections = unpack(window.IAV.motions[name]);
      // the vertices come as differences between frames (avatar/viewer/codec.py's differences_in_time)
      const stride = sections.vertices.length / meta.frames;
      for (let i = stride; i < sections.vertices.length; i++) sections.vertices[i] += sections.vertices[i - stride];
      motions[name] = { ...meta, sections };
    }
    return motions[name];
  }

  // --- three.js and Spark ---------------------------------------------------------------------------------------

  const canvas = $("render");
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  // the background as the project's renders have it (sRGB values: the renderer writes sRGB)
  renderer.setClearColor(new THREE.Color().setRGB(...manifest.background, THREE.SRGBColorSpace), 1);
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(30, 1, 0.01, 100);
  // Drawn as the project's rasterizer draws (avatar/render/gaussians/projection.py): 0.3 px^2 added to each 2D
  // covariance without rescaling the opacity (Spark's blurAmount would rescale it, as Mip-Splatting does), and
  // each Gaussian cut where its alpha falls below 1/255 (sqrt(2 ln 255) standard deviations at opacity 1).
  const spark = new SparkRenderer({
    renderer,
    preBlurAmount: 0.3,
    blurAmount: 0,
    maxStdDev: Math.sqrt(2 * Math.log(255)),
    minAlpha: 1 / 255,
  });
  scene.add(spark);
  const splats = new PackedSplats({ maxSplats: N });
  const mesh = new SplatMesh({ packedSplats: splats });
  scene.add(mesh);
  const controls = new OrbitControls(camera, canvas);
  let drawsOwed = 3; // draws still owed to a change: a few, since Spark sorts after the first
  const requestDraw = (count = 3) => {
    drawsOwed = Math.max(drawsOwed, count);
  };
  controls.addEventListener("change", () => requestDraw());
  let intrinsics = null; // {K, width, height, scale}

  // The projection of pinhole intrinsics K (OpenCV pixel convention: pixel centres at integers) on a canvas of
  // width x height pixels.
  function setProjection() {
    const { K, width, height, scale } = intrinsics;
    const W = width * scale;
    const H = height * scale;
    const fx = K[0][0] * scale;
    const fy = K[1][1] * scale;
    const cx = (K[0][2] + 0.5) * scale;
    const cy = (K[1][2] + 0.5) * scale;
    const near = camera.near;
    const far = camera.far;
    camera.projectionMatrix.set(
      (2 * fx) / W, 0, 1 - (2 * cx) / W, 0,
      0, (2 * fy) / H, (2 * cy) / H - 1, 0,
      0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
      0, 0, -1, 0,
    );
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  }
  camera.updateProjectionMatrix = () => intrinsics && setProjection();

  // Put the camera where capture camera `view` (K, world_to_cam, width, height) was, looking at the avatar.
  function placeCamera(view) {
    const scale = Number(params.get("scale")) || Math.max(1, Math.floor(Math.min(innerHeight - 160, innerWidth / 2 - 40) / view.height));
    intrinsics = { K: view.K, width: view.width, height: view.height, scale };
    renderer.setSize(view.width * scale, view.height * scale, true);
    const w2c = new THREE.Matrix4().fromArray(view.world_to_cam.flat()).transpose();
    const c2w = w2c.clone().invert();
    // OpenCV camera (x right, y down, z forward) -> three.js (x right, y up, looking down -z)
    c2w.multiply(new THREE.Matrix4().makeScale(1, -1, -1));
    c2w.decompose(camera.position, camera.quaternion, new THREE.Vector3());
    camera.up.set(0, 1, 0).applyQuaternion(camera.quaternion);
    const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(camera.quaternion);
    const centre = new THREE.Vector3(...manifest.centre);
    const depth = Math.max(centre.clone().sub(camera.position).dot(forward), 0.05);
    controls.target.copy(camera.position).addScaledVector(forward, depth);
    camera.updateMatrixWorld(true);
    setProjection();
    drawContactMarks();
    requestDraw();
  }

  // --- one frame ------------------------------------------------------------------------------------------------

  // Pose the current frame and hand it to Spark.
  function applyFrame() {
    const start = performance.now();
    poseFrame(avatar, motions[state.motion], state.frame, posed);
    upload();
    poseTimes.push(performance.now() - start);
    if (poseTimes.length > 120) poseTimes.shift();
    stats.pose_ms = median(poseTimes);
    updateControls();
  }

  // Hand the posed Gaussians to Spark, those of hidden parts transparent.
  function upload() {
    const packed = splats.ensureSplats(N);
    const { centers, scales, quats, rgba } = posed;
    for (let i = 0; i < N; i++) {
      const opacity = state.visible[statics.part[i]] ? rgba[4 * i + 3] : 0;
      setPackedSplat(
        packed, i,
        centers[3 * i], centers[3 * i + 1], centers[3 * i + 2],
        scales[3 * i], scales[3 * i + 1], scales[3 * i + 2],
        quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3], quats[4 * i],
        opacity, rgba[4 * i], rgba[4 * i + 1], rgba[4 * i + 2],
      );
    }
    splats.numSplats = N;
    splats.needsUpdate = true;
    mesh.updateVersion();
    requestDraw();
  }

  function updateControls() {
    const motion = motions[state.motion];
    $("timeline").max = motion.frames - 1;
    $("timeline").value = state.frame;
    const contact = motion.contact[state.frame] ? " (contact)" : "";
    $("frame-label").textContent = `frame ${state.frame + 1} / ${motion.frames}${contact}`;
    $("play").textContent = state.playing ? "pause" : "play";
    const view = motion.cameras.find((c) => c.id === state.camera);
    $("render-caption").textContent = `${manifest.label}, ${motion.label} (drag to orbit, wheel to zoom)`;
    const gt = $("gt");
    if (view && view.ground_truth) {
      gt.src = urlPath("data", "gt", motion.name, view.id, `${pad(state.frame)}.jpg`);
      gt.width = view.width * intrinsics.scale;
      gt.height = view.height * intrinsics.scale;
      $("gt-view").hidden = false;
      $("gt-caption").textContent = `ground truth, camera ${view.id}`;
    } else {
      $("gt-view").hidden = true;
    }
    $("stats").textContent =
      `${N} Gaussians · pose ${stats.pose_ms?.toFixed(1) ?? "-"} ms` +
      (stats.frame_ms ? ` · frame ${stats.frame_ms.toFixed(1)} ms` : "");
  }

  function drawContactMarks() {
    const motion = motions[state.motion];
    const box = $("contact-marks");
    box.replaceChildren();
    if (!motion) return;
    motion.contact.forEach((touching, t) => {
      if (!touching) return;
      const mark = document.createElement("div");
      mark.className = "contact-mark";
      mark.style.left = `${(100 * t) / Math.max(motion.frames - 1, 1)}%`;
      mark.title = `frame ${t + 1}: contact`;
      box.appendChild(mark);
    });
  }

  // --- what the user picks --------------------------------------------------------------------------------------

  async function selectMotion(name, frame = 0, cameraId = null) {
    const motion = await motionData(name);
    state.motion = name;
    state.frame = Math.min(Math.max(frame, 0), motion.frames - 1);
    $("motion").value = name;
    const cameraSelect = $("camera");
    cameraSelect.replaceChildren(
      ...motion.cameras.map((c) => new Option(`${c.id}${c.ground_truth ? "" : " (no ground truth)"}`, c.id)),
    );
    const view = motion.cameras.find((c) => c.id === cameraId) ?? motion.cameras[0];
    selectCamera(view.id);
    applyFrame();
  }

  function selectCamera(id) {
    const view = motions[state.motion].cameras.find((c) => c.id === id);
    state.camera = view.id;
    $("camera").value = view.id;
    placeCamera(view);
  }

  function step(delta) {
    const frames = motions[state.motion].frames;
    state.frame = (state.frame + delta + frames) % frames;
    applyFrame();
  }

  $("motion").replaceChildren(...manifest.motions.map((m) => new Option(m.label, m.name)));
  $("motion").addEventListener("change", (e) => selectMotion(e.target.value, 0, state.camera));
  $("camera").addEventListener("change", (e) => {
    selectCamera(e.target.value);
    updateControls();
  });
  $("timeline").addEventListener("input", (e) => {
    state.frame = Number(e.target.value);
    applyFrame();
  });
  $("prev").addEventListener("click", () => step(-1));
  $("next").addEventListener("click", () => step(1));
  $("play").addEventListener("click", () => {
    state.playing = !state.playing;
    frameIntervals.length = 0;
    updateControls();
  });
  manifest.parts.forEach((part, p) => {
    const box = $(`show-${part}`);
    if (!box) return;
    box.addEventListener("change", () => {
      state.visible[p] = box.checked;
      upload();
    });
  });
  addEventListener("keydown", (e) => {
    if (e.target.tagName === "SELECT") return;
    if (e.key === "ArrowLeft") step(-1);
    else if (e.key === "ArrowRight") step(1);
    else if (e.key === " ") $("play").click();
    else return;
    e.preventDefault();
  });

  // --- the loop -------------------------------------------------------------------------------------------------

  let lastAdvance = 0;
  let lastFrameTime = null;
  let frameCount = 0;
  // Drawn on demand: while playing, after a change (a frame, the camera, a toggle: requestDraw), and while Spark
  // sorts or asks for a draw (its dirty flag); an idle page draws nothing.
  renderer.setAnimationLoop((now) => {
    if (state.playing && motions[state.motion]) {
      if (lastFrameTime !== null) {
        frameIntervals.push(now - lastFrameTime);
        if (frameIntervals.length > 120) frameIntervals.shift();
        stats.frame_ms = median(frameIntervals);
      }
      if (now - lastAdvance >= 1000 / motions[state.motion].fps) {
        lastAdvance = now;
        step(1);
      }
    }
    lastFrameTime = state.playing ? now : null;
    const busy = spark.dirty || spark.sorting || spark.sortDirty;
    if (!state.playing && drawsOwed <= 0 && !busy) return;
    drawsOwed = Math.max(drawsOwed - 1, 0);
    renderer.render(scene, camera);
    frameCount++;
  });

  // Resolves once the current splats are sorted and drawn (at least `minimum` more frames, at most 5 s).
  function settle(minimum = 3) {
    requestDraw(minimum + 3);
    const start = frameCount;
    const deadline = performance.now() + 5000;
    let quiet = 0;
    return new Promise((resolve) => {
      const check = () => {
        quiet = spark.sorting || spark.sortDirty ? 0 : quiet + 1;
        if ((frameCount - start >= minimum && quiet >= 2) || performance.now() > deadline) resolve();
        else requestAnimationFrame(check);
      };
      requestAnimationFrame(check);
    });
  }

  async function show({ motion = state.motion, frame = state.frame, camera: cameraId = state.camera } = {}) {
    if (motion !== state.motion) await selectMotion(motion, frame, cameraId);
    else {
      if (cameraId !== state.camera) selectCamera(cameraId);
      state.frame = frame;
      applyFrame();
    }
    await settle();
  }

  const first = manifest.motions.find((m) => m.name === params.get("motion")) ?? manifest.motions[0];
  const ready = selectMotion(first.name, Number(params.get("frame") || 0), params.get("camera")).then(settle);
  // posed(): the current frame's Gaussians as the page computed them (for tests against avatar/viewer/codec.py)
  const posedArrays = () => Object.fromEntries(Object.entries(posed).map(([k, v]) => [k, Array.from(v)]));
  window.viewer = { ready, show, settle, state, stats, gaussians: N, posed: posedArrays, draws: () => frameCount };
  ready.then(() => {
    document.body.dataset.ready = "true";
  });
}

main().catch((error) => {
  window.viewerFailed = true;
  $("message").textContent = `The viewer could not start: ${error.message}`;
  console.error(error);
});
