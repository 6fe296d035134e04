// The therapist's view: the patient and fraction, the beam-hold lamp and the eye's deviation
// live from /ws/pose, start and stop of tracking, the position verification's verdict and the
// camera images: while tracking, the tracked unit's live frames (GET /tracking/preview, a few
// per second: the frames tracking already has, no extra exposure); otherwise the newest
// capture's.
//
// While the daily QA locks position verification and tracking (ctx.qa, GET /qa/status) a banner
// says so with the daemon's reason and whom to call, and Verify and Start tracking are disabled
// (their title says why); the daemon would answer them 409 with the same reason.
//
// The lamp shows the daemon's beam-hold flag as the pose stream carries it (pose, hold and
// heartbeat messages). It is a display, not the interlock: when the stream has said nothing
// for LINK_DEAD_MS it shows the beam held, as the daemon asks of every listener.

import {at, get, hangUp, objectUrl, post, reasonOf, request, socket} from "../api.js";
import {field, h, message, num, panel, replace, signed, when} from "../dom.js";
import {DeviationPlot} from "../plot.js";

const LINK_DEAD_MS = 2500; // heartbeats come every second when nothing else does
const TRACKING_POLL_MS = 1000;
const IMAGE_REFRESH_MS = 2000; // camera images at a reduced rate: at most one capture per 2 s
const LIVE_MS = 400; // live images while tracking: 2.5 a second, a tenth of the camera rate

export function mount(container, ctx) {
  let patient = null;
  let fraction = 1;
  let poseSocket = null;
  let lastWord = 0;
  let closed = false;
  let trackingRunning = false;
  let trackingAsked = null; // the GET /tracking under way, shared by whoever asks meanwhile
  let imageTimer = null;
  let imagePending = false;
  let lastImages = 0;
  let liveTimer = null;
  let liveUnit = null; // the unit whose live images are shown (null: not tracking)
  let livePending = null; // the live images' fetch under way (a promise), or null
  let stopping = false; // a stop asked: no status starts the live images again meanwhile
  const liveUrls = new Map(); // camera -> the blob: URL its <img> shows
  const timers = [];

  // --- patient and fraction ------------------------------------------------------------
  const patientInput = h("input", {id: "patient-id", type: "text", required: true,
    spellcheck: "false", autocomplete: "off", placeholder: "P-0001", size: 14});
  const fractionInput = h("input", {id: "fraction", type: "number", min: 1, max: 1000,
    value: 1, required: true, class: "narrow"});
  const patientForm = h("form", {class: "inline", id: "patient-form"},
    h("label", {}, "Patient ", patientInput), h("label", {}, "Fraction ", fractionInput),
    h("button", {type: "submit", id: "patient-load", class: "primary"}, "Load"));
  const patientDetails = h("dl", {class: "facts", id: "patient-details"});
  const referenceDetails = h("div", {id: "reference-details"});
  const patientMessage = h("div", {id: "patient-message"});
  // Either role: the therapist who sets the patient up captures the reference (docs/security.md).
  const referenceActions = h("div", {class: "actions"},
    h("button", {type: "button", id: "reference-capture", disabled: true,
      title: "Measure the eye now and make it the fraction's next reference",
      onclick: captureReference}, "Capture reference at set-up"));

  // --- lamp, tracking, deviation ---------------------------------------------------------
  const lampText = h("span", {class: "lamp-text"}, "…");
  const lampReason = h("span", {class: "lamp-reason", id: "beam-reason"}, "waiting for the "
    + "pose stream");
  const lamp = h("div", {id: "beam-lamp", class: "lamp", role: "status", "aria-live": "polite",
    dataset: {hold: "unknown", link: "connecting"}}, lampText, lampReason);
  const startButton = h("button", {type: "button", id: "tracking-start", class: "primary",
    disabled: true, onclick: startTracking}, "Start tracking");
  const stopButton = h("button", {type: "button", id: "tracking-stop", disabled: true,
    onclick: stopTracking}, "Stop tracking");
  const trackingFacts = h("dl", {class: "facts", id: "tracking-status"});
  const trackingMessage = h("div", {id: "tracking-message"});
  const readouts = {};
  const readoutRow = h("div", {class: "readouts", id: "readouts"},
    ["ΔX", "ΔY", "ΔZ", "|Δ|", "gaze", "confidence", "latency"].map((name) => {
      readouts[name] = h("span", {class: "value"}, "–");
      return h("div", {class: "readout"}, h("span", {class: "label"}, name), readouts[name]);
    }));
  const canvas = h("canvas", {id: "deviation-plot", class: "plot", width: 800, height: 320});
  const plot = new DeviationPlot(canvas);

  // --- verification and cameras -----------------------------------------------------------
  const verifyButton = h("button", {type: "button", id: "verify", class: "primary",
    disabled: true, onclick: verify}, "Verify position");
  const verdict = h("div", {id: "verdict", class: "verdict", dataset: {passed: "none"}},
    h("p", {class: "muted"}, "No measurement of this fraction yet."));
  const captureButton = h("button", {type: "button", id: "capture", onclick: capture},
    "Capture");
  const captureCaption = h("p", {id: "capture-caption", class: "muted"}, "No capture yet.");
  const images = h("div", {id: "camera-images", class: "images"});
  const captureMessage = h("div", {id: "capture-message"});

  // --- the daily QA's lockout ---------------------------------------------------------------
  const qaLock = h("div", {id: "qa-lock", class: "qa-lock", role: "alert", hidden: true});

  container.append(qaLock, h("div", {class: "grid therapist"},
    h("div", {class: "column"},
      panel("Patient and fraction", patientForm, patientMessage, patientDetails,
        referenceDetails, referenceActions),
      panel("Position verification", h("div", {class: "actions"}, verifyButton), verdict)),
    h("div", {class: "column wide"},
      h("section", {class: "panel lamp-panel"}, lamp,
        h("div", {class: "actions"}, startButton, stopButton), trackingMessage, trackingFacts),
      panel("Deviation from the reference", readoutRow, canvas,
        h("p", {class: "muted small"}, "Green band: the patient's tolerance (translation on "
          + "each axis, gaze angle). Bar: beam held (red) or clear (green)."))),
    h("div", {class: "column"},
      panel("Cameras", h("div", {class: "actions"}, captureButton), captureMessage,
        captureCaption, images))));

  patientForm.addEventListener("submit", (event) => {
    event.preventDefault();
    loadPatient(patientInput.value.trim(), Number(fractionInput.value));
  });

  // --- the patient -----------------------------------------------------------------------
  async function loadPatient(id, number) {
    replace(patientMessage);
    replace(patientDetails);
    replace(referenceDetails);
    patient = null;
    fraction = number;
    updateButtons();
    if (!id) return;
    try {
      patient = await get(at("patients", id));
    } catch (error) {
      replace(patientMessage, message("error", reasonOf(error)));
      return;
    }
    plot.setTolerance(patient.tolerance_mm, patient.tolerance_gaze_deg);
    replace(patientDetails,
      field("Patient", patient.patient_id), field("Treated eye", patient.eye),
      field("Unit", patient.unit),
      field("Tolerance", `${num(patient.tolerance_mm, 2)} mm, ${num(
        patient.tolerance_gaze_deg, 1)}°`),
      field("Min. confidence", num(patient.min_confidence, 2)),
      field("Eye model", patient.eye_model_version === null ? "population defaults"
        : `version ${patient.eye_model_version}`));
    updateButtons();
    await Promise.all([loadReference(), loadVerdict()]);
    refreshImages();
  }

  async function loadReference() {
    try {
      const reference = await get(at("patients", patient.patient_id, "fractions", fraction,
        "reference"));
      const pose = reference.pose || {};
      replace(referenceDetails, h("h3", {}, `Reference of fraction ${fraction}`),
        h("dl", {class: "facts"},
          field("Version", `${reference.version} (${reference.source})`),
          field("Centre", (pose.centre_mm || []).map((v) => num(v, 2)).join(", ") + " mm"),
          field("Gaze", (pose.gaze || []).map((v) => num(v, 3)).join(", ")),
          field("Made", `${when(reference.created)} by ${reference.actor}`)));
    } catch (error) {
      replace(referenceDetails, message("error", reasonOf(error)));
    }
  }

  async function loadVerdict() {
    try {
      const found = await get("/pose/measurements", {query: {patient_id: patient.patient_id,
        fraction, limit: 1}});
      showVerdict(found.items[0] || null);
    } catch (error) {
      replace(verdict, message("error", reasonOf(error)));
    }
  }

  function showVerdict(measurement) {
    if (!measurement) {
      verdict.dataset.passed = "none";
      replace(verdict, h("p", {class: "muted"}, "No measurement of this fraction yet."));
      return;
    }
    const deviation = measurement.deviation || {};
    const delta = deviation.delta_mm || [];
    verdict.dataset.passed = String(measurement.passed);
    replace(verdict,
      h("p", {class: `verdict-word ${measurement.passed ? "pass" : "fail"}`},
        measurement.passed ? "PASSED" : "FAILED"),
      h("dl", {class: "facts"},
        field("ΔX ΔY ΔZ", delta.map((v) => signed(v, 3)).join("  ") + " mm"),
        field("|Δ|", `${num(deviation.length_mm, 3)} mm`),
        field("Gaze", `${num(deviation.gaze_deg, 2)}°`),
        field("Confidence", num(measurement.pose?.confidence, 2)),
        field("Measured", `${when(measurement.created)} by ${measurement.actor}`),
        field("Id", measurement.id)),
      measurement.reasons?.length ? h("ul", {class: "reasons"},
        measurement.reasons.map((r) => h("li", {}, r))) : null);
  }

  async function verify() {
    if (!patient) return;
    verifyButton.disabled = true;
    replace(verdict, h("p", {class: "muted"}, "Measuring…"));
    try {
      showVerdict(await post("/pose/measure", {patient_id: patient.patient_id, fraction}));
    } catch (error) {
      verdict.dataset.passed = "none";
      replace(verdict, message("error", reasonOf(error)));
    } finally {
      updateButtons();
    }
  }

  async function captureReference() {
    if (!patient) return;
    if (!window.confirm(`Measure the eye now and make it the reference of fraction ${fraction} `
        + `of ${patient.patient_id} (a new version; the earlier ones are kept)?`)) return;
    const button = document.getElementById("reference-capture");
    button.disabled = true;
    replace(referenceDetails, h("p", {class: "muted"}, "Capturing the reference…"));
    try {
      await post(at("patients", patient.patient_id, "fractions", fraction, "reference",
        "capture"));
    } catch (error) {
      replace(patientMessage, message("error", reasonOf(error)));
    }
    await loadReference();
    updateButtons();
  }

  // --- tracking and the pose stream -------------------------------------------------------
  async function startTracking() {
    if (!patient) return;
    startButton.disabled = true;
    replace(trackingMessage, h("p", {class: "muted"}, "Starting (the workers load the "
      + "calibration, a few seconds)…"));
    try {
      await post("/tracking/start", {patient_id: patient.patient_id, fraction});
      plot.clear();
      replace(trackingMessage);
    } catch (error) {
      replace(trackingMessage, message("error", reasonOf(error)));
    }
    await pollTracking();
  }

  async function stopTracking() {
    stopButton.disabled = true;
    stopping = true;
    setLive(null); // no preview asked of a session that is ending,
    await livePending; // nor one still on its way when the stop arrives (a 409 otherwise)
    try {
      await post("/tracking/stop");
      replace(trackingMessage);
    } catch (error) {
      replace(trackingMessage, message("error", reasonOf(error)));
    }
    // A status asked before the stop (still "running") must not start the live images again
    // (a CI run saw the 409 of a preview asked that way): it is let through first.
    await trackingAsked;
    stopping = false;
    await pollTracking();
  }

  /** Ask the daemon how tracking goes (one request at a time, however often asked). */
  function pollTracking() {
    if (!trackingAsked) {
      trackingAsked = showTracking().finally(() => {
        trackingAsked = null;
      });
    }
    return trackingAsked;
  }

  async function showTracking() {
    let status;
    try {
      status = await get("/tracking");
    } catch {
      return;
    }
    if (closed) return;
    trackingRunning = status.running;
    lamp.dataset.tracking = String(status.running);
    // Previews only once the session has a frame (it warms its workers first: a few s).
    setLive(status.running && status.frames_acquired > 0 && !stopping ? status.unit : null);
    replace(trackingFacts,
      field("Tracking", status.running ? `running (${status.patient_id ?? "?"}, fraction `
        + `${status.fraction ?? "?"})` : "stopped"),
      field("Frames", `${status.frames_processed} processed of ${status.frames_acquired}; `
        + `${status.frames_dropped} dropped, ${status.frames_missed} missed, `
        + `${status.frames_held} held`),
      status.stalled ? field("Stalled", `${status.stalled.reason}`) : null,
      status.error ? field("Ended by", status.error) : null);
    if (status.running && !patient && status.patient_id) {
      // Tracking started elsewhere: show whom it tracks.
      patientInput.value = status.patient_id;
      fractionInput.value = status.fraction;
      await loadPatient(status.patient_id, status.fraction);
    }
    updateButtons();
  }

  function setLamp(hold, reason) {
    lamp.dataset.hold = hold === null ? "unknown" : String(hold);
    lampText.textContent = hold === null ? "NO LINK" : hold ? "BEAM HOLD" : "BEAM CLEAR";
    lampReason.textContent = reason;
  }

  function onPose(event) {
    lastWord = Date.now();
    lamp.dataset.link = "up";
    const data = JSON.parse(event.data);
    if (data.type === "pose") {
      const deviation = data.deviation || null;
      const hold = data.beam_hold !== false; // fail safe: only an explicit false clears
      const reasons = data.reasons?.length ? data.reasons.join(", ") : data.eye || "";
      setLamp(hold, hold ? reasons : "in tolerance");
      plot.push({timeMs: Date.now(), delta_mm: deviation?.delta_mm ?? null,
        gaze_deg: deviation?.gaze_deg ?? null, hold});
      const d = deviation?.delta_mm || [];
      readouts["ΔX"].textContent = signed(d[0]);
      readouts["ΔY"].textContent = signed(d[1]);
      readouts["ΔZ"].textContent = signed(d[2]);
      readouts["|Δ|"].textContent = num(deviation?.length_mm, 3);
      readouts.gaze.textContent = num(deviation?.gaze_deg, 2) + "°";
      readouts.confidence.textContent = num(data.confidence, 2);
      readouts.latency.textContent = num(data.latency_ms, 0) + " ms";
      if (!trackingRunning) pollTracking();
    } else if (data.type === "hold") {
      setLamp(true, `held: ${data.reason}`);
      plot.push({timeMs: Date.now(), delta_mm: null, gaze_deg: null, hold: true});
      if (data.reason === "ended") pollTracking();
    } else if (data.type === "heartbeat") {
      setLamp(data.beam_hold !== false, data.tracking ? (data.stalled ? `stalled: ${
        data.stalled.reason}` : "tracking") : "not tracking");
      if (data.tracking !== trackingRunning) pollTracking();
    }
  }

  function openPose() {
    if (closed) return;
    const ws = socket("/ws/pose");
    poseSocket = ws;
    lastWord = Date.now();
    ws.onmessage = onPose;
    ws.onclose = (close) => {
      if (closed || poseSocket !== ws) return;
      lamp.dataset.link = "lost";
      setLamp(true, close.code === 1008 ? `refused: ${close.reason}`
        : "pose stream closed: reconnecting");
      if (close.code !== 1008) timers.push(setTimeout(openPose, 1000));
    };
  }

  function watchLink() {
    if (Date.now() - lastWord > LINK_DEAD_MS && lamp.dataset.link !== "lost") {
      lamp.dataset.link = "lost";
      setLamp(true, `no word from the daemon for ${LINK_DEAD_MS / 1000} s: the link counts `
        + "as dead");
    }
  }

  // --- camera images ----------------------------------------------------------------------
  /** Show the live images of `unit` (a unit id, "all") while tracking, or the newest capture's
   * (null). */
  function setLive(unit) {
    if (unit && !liveTimer) {
      liveUnit = unit;
      liveTimer = setInterval(showLive, LIVE_MS);
      showLive();
    } else if (!unit && liveTimer) {
      clearInterval(liveTimer);
      liveTimer = null;
      liveUnit = null;
      delete images.dataset.live;
      delete images.dataset.frame;
      delete images.dataset.capture; // the newest capture is shown again
      forgetLiveUrls();
      refreshImages();
    }
  }

  function forgetLiveUrls() {
    liveUrls.forEach((src) => URL.revokeObjectURL(src));
    liveUrls.clear();
  }

  function showLive() {
    if (livePending || closed || !liveUnit) return;
    livePending = fetchLive().finally(() => { livePending = null; });
  }

  async function fetchLive() {
    const units = (ctx.status?.units || []).filter((u) => liveUnit === "all" || u.id === liveUnit);
    const fetched = [];
    try {
      let frame = null;
      for (const unit of units) {
        for (const camera of unit.cameras) {
          if (closed || !liveTimer) return; // tracking stopped meanwhile: ask no more
          const response = await request("GET", `/tracking/preview/${encodeURIComponent(
            camera)}.jpg`, {raw: true});
          frame = response.headers.get("X-Frame");
          fetched.push([unit, camera, URL.createObjectURL(await response.blob())]);
        }
      }
      if (closed || !liveTimer) return;
      if (images.dataset.live !== "true") {
        forgetLiveUrls();
        replace(images, fetched.map(([unit, camera]) => h("figure", {class: "camera"},
          h("img", {alt: `camera ${camera}, live`, dataset: {camera}}),
          h("figcaption", {}, `${camera} (unit ${unit.id}), live`))));
        images.dataset.live = "true";
      }
      for (const [, camera, src] of fetched) {
        const img = images.querySelector(`img[data-camera="${camera}"]`);
        if (!img) continue;
        img.src = src; // the decoded picture stays on screen until the new one is decoded
        const old = liveUrls.get(camera);
        if (old) URL.revokeObjectURL(old);
        liveUrls.set(camera, src);
      }
      fetched.length = 0; // handed over: not revoked below
      images.dataset.frame = frame ?? "";
      captureCaption.textContent = `Live: unit ${liveUnit}, camera frame ${frame}`;
      replace(captureMessage);
    } catch (error) {
      // 409: tracking ended between two looks; the next status poll shows the captures again.
      if (error.status !== 409) replace(captureMessage, message("error", reasonOf(error)));
    } finally {
      fetched.forEach(([, , src]) => URL.revokeObjectURL(src));
    }
  }

  async function capture() {
    captureButton.disabled = true;
    replace(captureMessage);
    try {
      await post("/captures", {unit: patient?.unit || "all"});
    } catch (error) {
      replace(captureMessage, message("error", reasonOf(error)));
    } finally {
      captureButton.disabled = false;
    }
    refreshImages();
  }

  /** Fetch the newest capture's images, at most once per IMAGE_REFRESH_MS. */
  function refreshImages() {
    const wait = lastImages + IMAGE_REFRESH_MS - Date.now();
    if (wait > 0) {
      if (!imageTimer) imageTimer = setTimeout(() => {
        imageTimer = null;
        refreshImages();
      }, wait);
      return;
    }
    if (imagePending) return;
    imagePending = true;
    lastImages = Date.now();
    showNewestCapture().finally(() => {
      imagePending = false;
    });
  }

  async function showNewestCapture() {
    let newest;
    try {
      newest = (await get("/captures", {query: {limit: 1, kind: "measurement"}})).items[0];
    } catch (error) {
      replace(captureMessage, message("error", reasonOf(error)));
      return;
    }
    if (!newest) {
      captureCaption.textContent = "No capture yet.";
      return;
    }
    if (images.dataset.capture === newest.id || liveTimer) return;
    const units = ctx.status?.units || [];
    // A capture of every unit holds one frame per unit in the rig's order (FORMATS.md); a
    // capture of one unit holds that unit's frame as frame 0.
    const frames = newest.unit === "all" ? units.map((u, k) => [k, u])
      : [[0, units.find((u) => u.id === newest.unit)]].filter(([, u]) => u);
    const tiles = [];
    for (const [frame, unit] of frames) {
      for (const camera of unit.cameras) {
        const shown = !patient || patient.unit === "all" || patient.unit === unit.id;
        if (!shown) continue;
        try {
          const src = await objectUrl(at("captures", newest.id, "frames", frame,
            `${camera}.png`));
          tiles.push(h("figure", {class: "camera"}, image(src, `camera ${camera}`, camera),
            h("figcaption", {}, `${camera} (unit ${unit.id})`)));
        } catch (error) {
          tiles.push(h("figure", {class: "camera"}, message("error", reasonOf(error))));
        }
      }
    }
    if (closed || liveTimer) return; // tracking began meanwhile: the live images stay
    images.dataset.capture = newest.id;
    replace(images, tiles);
    captureCaption.textContent = `${newest.id} — unit ${newest.unit}, ${when(newest.created)}`;
  }

  function onDaemonEvent(event) {
    const data = event.detail;
    if (data.type === "capture.stored" && !liveTimer) refreshImages();
  }

  /** The banner of the daily QA's lockout: locked (why, whom to call), or overridden. */
  function showQa() {
    const status = ctx.qa;
    const overridden = status && !status.locked && status.override;
    qaLock.hidden = !status?.locked && !overridden;
    qaLock.dataset.kind = status?.locked ? "locked" : overridden ? "override" : "none";
    if (status?.locked) {
      replace(qaLock, h("strong", {}, "Position verification and tracking are locked by the "
        + "daily QA."),
      h("div", {}, "Why: ", h("span", {id: "qa-lock-reason"}, status.reason)),
      h("div", {class: "qa-lock-help"}, "Call the physicist, or run the daily QA with the QA "
        + "phantom in place: ", h("a", {href: "#/qa"}, "Daily QA"), "."));
    } else if (overridden) {
      replace(qaLock, h("strong", {}, "The daily QA's lockout is overridden"),
        ` by ${status.override.actor} until ${when(status.override.until)}: `
          + `“${status.override.reason}”. The QA lacks: ${status.qa_reason}`);
    } else {
      replace(qaLock);
    }
    updateButtons();
  }

  function updateButtons() {
    const loaded = patient !== null;
    const state = ctx.status?.state;
    const locked = ctx.qa?.locked === true;
    const why = locked ? `Locked by the daily QA: ${ctx.qa.reason}` : null;
    startButton.disabled = !loaded || trackingRunning || locked;
    stopButton.disabled = !trackingRunning;
    verifyButton.disabled = !loaded || trackingRunning || locked;
    for (const button of [startButton, verifyButton]) {
      if (why) button.title = why;
      else button.removeAttribute("title");
    }
    captureButton.disabled = trackingRunning || state === "calibrating";
    const referenceButton = document.getElementById("reference-capture");
    if (referenceButton) referenceButton.disabled = !loaded || trackingRunning;
  }

  const onStatus = () => updateButtons();
  ctx.events.addEventListener("event", onDaemonEvent);
  ctx.events.addEventListener("status", onStatus);
  ctx.events.addEventListener("qa", showQa);
  showQa();
  openPose();
  timers.push(setInterval(watchLink, 500));
  timers.push(setInterval(pollTracking, TRACKING_POLL_MS));
  pollTracking();
  refreshImages();
  plot.draw();

  return () => {
    closed = true;
    ctx.events.removeEventListener("event", onDaemonEvent);
    ctx.events.removeEventListener("status", onStatus);
    ctx.events.removeEventListener("qa", showQa);
    timers.forEach((t) => {
      clearInterval(t);
      clearTimeout(t);
    });
    clearTimeout(imageTimer);
    clearInterval(liveTimer);
    forgetLiveUrls();
    if (poseSocket) hangUp(poseSocket);
  };
}


/** An <img> of a blob: URL, which it lets go once decoded (or failed): no URL outlives it. */
function image(src, alt, camera) {
  const element = h("img", {alt, dataset: {camera}});
  const release = () => URL.revokeObjectURL(src);
  element.addEventListener("load", release, {once: true});
  element.addEventListener("error", release, {once: true});
  element.src = src;
  return element;
}
