// matscan relighting viewer: the reconstructed maps under a point light you drag.
// The fragment shader is shared/design.md's image formation with the paper's Eq. 1
// (GGX, uncorrelated Smith, Schlick), the same model the maps were fitted with.
// Emission is added to the reflected light and alpha composites the sample over a checkerboard.
// Reads its data from the page: window.MATSCAN_VIEWER = {field_mm, camera_mm, camera_w, R, textures: {...}}.
// With ?stats=1 in the page's address it also writes the canvas's mean and spread into the DOM
// (for tests: reading the canvas back stalls the GPU, so a normal view never does).
(function () {
  "use strict";
  var status = document.getElementById("viewer-status");
  function report(msg) {
    if (status) status.textContent = msg;
    document.body.setAttribute("data-viewer", msg);
  }
  window.addEventListener("error", function (e) { report("error: " + e.message); });

  var cfg = window.MATSCAN_VIEWER;
  var canvas = document.getElementById("viewer");
  var gl = canvas && (canvas.getContext("webgl", {preserveDrawingBuffer: true}) ||
                      canvas.getContext("experimental-webgl", {preserveDrawingBuffer: true}));
  if (!gl) { report("error: WebGL is not available"); return; }

  var vs = [
    "attribute vec2 a_pos;",
    "varying vec2 v_uv;",
    "void main() { v_uv = vec2(0.5 * (a_pos.x + 1.0), 0.5 * (1.0 - a_pos.y)); gl_Position = vec4(a_pos, 0.0, 1.0); }"
  ].join("\n");

  var fs = [
    "precision highp float;",
    "varying vec2 v_uv;",
    "uniform sampler2D u_diffuse, u_specular, u_roughness, u_normal, u_emissive, u_alpha;",
    "uniform vec2 u_field;      // mm (width, height)",
    "uniform vec3 u_light;      // mm",
    "uniform vec3 u_camera;     // mm",
    "uniform float u_camera_w;  // 1: a camera centre; 0: orthographic, u_camera is R * its direction",
    "uniform float u_R;         // reference distance, mm",
    "uniform float u_exposure;",
    "const float PI = 3.14159265358979;",
    "vec3 srgb_to_linear(vec3 c) {",
    "  return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(0.04045, c));",
    "}",
    "vec3 linear_to_srgb(vec3 c) {",
    "  c = clamp(c, 0.0, 1.0);",
    "  return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));",
    "}",
    "void main() {",
    "  vec3 rho = srgb_to_linear(texture2D(u_diffuse, v_uv).rgb);",
    "  vec3 f0 = srgb_to_linear(texture2D(u_specular, v_uv).rgb);",
    "  float r = texture2D(u_roughness, v_uv).r;",
    "  vec3 n = normalize(texture2D(u_normal, v_uv).rgb * 2.0 - 1.0);",
    "  // pixel centre in the sample frame: x grows with columns, y with -rows",
    "  vec3 p = vec3((v_uv.x - 0.5) * u_field.x, (0.5 - v_uv.y) * u_field.y, 0.0);",
    "  vec3 lv = u_light - p; float d = length(lv); vec3 l = lv / d;",
    "  vec3 v = normalize(u_camera - u_camera_w * p);",
    "  vec3 h = normalize(l + v);",
    "  float nl = dot(n, l), nv = dot(n, v);",
    "  float nh = max(dot(n, h), 0.0), vh = clamp(dot(v, h), 0.0, 1.0);",
    "  float a = max(r * r, 1e-3), a2 = a * a;",
    "  float den = nh * nh * (a2 - 1.0) + 1.0;",
    "  float D = a2 / (PI * den * den);",
    "  float nlc = max(nl, 1e-7), nvc = max(nv, 1e-7);",
    "  float G = (2.0 * nlc / (nlc + sqrt(a2 + (1.0 - a2) * nlc * nlc))) *",
    "            (2.0 * nvc / (nvc + sqrt(a2 + (1.0 - a2) * nvc * nvc)));",
    "  vec3 F = f0 + (1.0 - f0) * pow(1.0 - vh, 5.0);",
    "  vec3 spec = (nl > 0.0 && nv > 0.0) ? D * G * F / (4.0 * nlc * nvc) : vec3(0.0);",
    "  vec3 fr = rho / PI + spec;",
    "  // isotropic light of intensity 1: pi * I * (R/d)^2 * f_r * max(n.l, 0)",
    "  vec3 radiance = PI * (u_R / d) * (u_R / d) * fr * max(nl, 0.0);",
    "  radiance += srgb_to_linear(texture2D(u_emissive, v_uv).rgb);  // light the sample gives off",
    "  float alpha = texture2D(u_alpha, v_uv).r;",
    "  float check = mod(floor(gl_FragCoord.x / 16.0) + floor(gl_FragCoord.y / 16.0), 2.0);",
    "  vec3 behind = vec3(0.35 + 0.3 * check);  // a checkerboard shows through holes",
    "  gl_FragColor = vec4(mix(behind, linear_to_srgb(radiance * u_exposure), alpha), 1.0);",
    "}"
  ].join("\n");

  function compile(type, src) {
    var s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  var prog = gl.createProgram();
  gl.attachShader(prog, compile(gl.VERTEX_SHADER, vs));
  gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) { report("error: " + gl.getProgramInfoLog(prog)); return; }
  gl.useProgram(prog);

  var buf = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buf);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
  var loc = gl.getAttribLocation(prog, "a_pos");
  gl.enableVertexAttribArray(loc);
  gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);

  var names = ["diffuse", "specular", "roughness", "normal", "emissive", "alpha"];
  var loaded = 0;
  names.forEach(function (name, unit) {
    var tex = gl.createTexture();
    var img = new Image();
    img.onload = function () {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, img);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      gl.uniform1i(gl.getUniformLocation(prog, "u_" + name), unit);
      loaded += 1;
      if (loaded === names.length) draw();
    };
    img.onerror = function () { report("error: texture " + name + " did not load"); };
    img.src = cfg.textures[name];
  });

  var params = new URLSearchParams(window.location.search);
  var height = cfg.R * Math.sin(Math.PI / 4);
  var light = [0, 0, height];
  if (params.get("light")) {
    var xyz = params.get("light").split(",").map(Number);
    if (xyz.length === 3 && xyz.every(isFinite)) light = xyz;
  }
  var exposure = document.getElementById("viewer-exposure");
  var readout = document.getElementById("viewer-light");

  function draw() {
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.uniform2f(gl.getUniformLocation(prog, "u_field"), cfg.field_mm[0], cfg.field_mm[1]);
    gl.uniform3f(gl.getUniformLocation(prog, "u_light"), light[0], light[1], light[2]);
    gl.uniform3f(gl.getUniformLocation(prog, "u_camera"), cfg.camera_mm[0], cfg.camera_mm[1], cfg.camera_mm[2]);
    gl.uniform1f(gl.getUniformLocation(prog, "u_camera_w"), cfg.camera_w === undefined ? 1.0 : cfg.camera_w);
    gl.uniform1f(gl.getUniformLocation(prog, "u_R"), cfg.R);
    gl.uniform1f(gl.getUniformLocation(prog, "u_exposure"), exposure ? Number(exposure.value) : 1.0);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    if (readout) readout.textContent = light.map(function (c) { return c.toFixed(0); }).join(", ");
    var err = gl.getError();
    report(err === gl.NO_ERROR ? "ok" : "error: WebGL error " + err);
    if (params.get("stats") === "1") stats();
  }

  function stats() {  // the canvas's mean and spread, for tests (a read-back: only when asked)
    var px = new Uint8Array(canvas.width * canvas.height * 4);
    gl.readPixels(0, 0, canvas.width, canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
    var sum = 0, sq = 0, count = canvas.width * canvas.height;
    for (var i = 0; i < px.length; i += 4) { var y = (px[i] + px[i + 1] + px[i + 2]) / 765; sum += y; sq += y * y; }
    var mean = sum / count;
    canvas.setAttribute("data-mean", mean.toFixed(5));
    canvas.setAttribute("data-std", Math.sqrt(Math.max(sq / count - mean * mean, 0)).toFixed(5));
  }

  function move(ev) {
    var rect = canvas.getBoundingClientRect();
    var u = (ev.clientX - rect.left) / rect.width, v = (ev.clientY - rect.top) / rect.height;
    // drag over the image: the light moves over the sample, at its height, as far out as
    // 1.5 times the larger of the field and that height (far enough to graze a small field
    // under a distant light, as RTI rigs have)
    var reach = 1.5 * Math.max(cfg.field_mm[0], cfg.field_mm[1], light[2]);
    light = [(u - 0.5) * 2 * reach, (0.5 - v) * 2 * reach, light[2]];
    draw();
  }
  var dragging = false;
  canvas.addEventListener("mousedown", function (ev) { dragging = true; move(ev); });
  window.addEventListener("mouseup", function () { dragging = false; });
  canvas.addEventListener("mousemove", function (ev) { if (dragging) move(ev); });
  if (exposure) exposure.addEventListener("input", draw);
})();
