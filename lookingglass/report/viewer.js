/* report.html's 3D view: the meshes (GLB, base64) and camera frusta of #lg-data, drawn with the
   bundled three.js (global LG3: lookingglass/report/static/three-bundle.min.js). */
(function () {
  'use strict';
  var T = window.LG3;
  var log = window.lgLog;
  var data = JSON.parse(document.getElementById('lg-data').textContent);
  var box = document.getElementById('viewer');
  var canvas = document.getElementById('lg-canvas');
  var controlsBox = document.getElementById('viewer-controls');

  var renderer = new T.WebGLRenderer({ canvas: canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.outputColorSpace = T.SRGBColorSpace;

  var scene = new T.Scene();
  scene.background = new T.Color(0xf7f8fa);
  var center = new T.Vector3().fromArray(data.center);
  var radius = data.radius;
  var camera = new T.PerspectiveCamera(35, 1, radius / 100, radius * 200);
  scene.add(camera);
  scene.add(new T.HemisphereLight(0xffffff, 0x6b7280, 1.6));
  var headlight = new T.DirectionalLight(0xffffff, 1.6);  // follows the camera, from its upper left
  headlight.position.set(-1, 1.2, 0.4);
  camera.add(headlight);
  headlight.target.position.set(0, 0, -1);
  camera.add(headlight.target);

  var controls = new T.OrbitControls(camera, canvas);
  controls.target.copy(center);

  var pending = false;
  function render() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(function () {
      pending = false;
      renderer.render(scene, camera);
      if (log.layers === data.layers.length && !log.rendered) {
        log.rendered = true;
        var r = canvas.getBoundingClientRect();
        log.canvas = { x: r.left + window.scrollX, y: r.top + window.scrollY, width: r.width, height: r.height };
        window.lgPut();
      }
    });
  }
  controls.addEventListener('change', render);

  function resize() {
    var w = Math.max(box.clientWidth, 1), h = Math.max(box.clientHeight, 1);
    renderer.setSize(w, h, false);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
    render();
  }
  new ResizeObserver(resize).observe(box);

  // The first view: from above the upper ring of cameras, between input cameras 0 and 1 (the
  // paper's rigs space them 72 degrees apart), close enough for the object to fill half the height.
  function home() {
    var toCam = new T.Vector3(0, 0, 1);
    if (data.views.length) toCam.fromArray(data.views[0].origin).sub(center);
    var azimuth = Math.atan2(toCam.x, toCam.z) + 0.63, polar = 0.6;  // radians; polar from +y
    var dir = new T.Vector3(Math.sin(polar) * Math.sin(azimuth), Math.cos(polar), Math.sin(polar) * Math.cos(azimuth));
    camera.fov = 35;
    camera.position.copy(center).addScaledVector(dir, 5.5 * radius);
    controls.target.copy(center);
    camera.updateProjectionMatrix();
    controls.update();
    render();
  }

  function fromView(i) {
    var v = data.views[i];
    camera.fov = v.fov_y_deg;
    camera.position.fromArray(v.origin);
    controls.target.fromArray(v.target);
    camera.updateProjectionMatrix();
    controls.update();
    render();
  }

  function base64ToBuffer(text) {
    var bin = atob(text), bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return bytes.buffer;
  }

  function addToggle(label, colour, checked, onChange) {
    var row = document.createElement('label');
    var input = document.createElement('input');
    input.type = 'checkbox';
    input.checked = checked;
    input.addEventListener('change', function () { onChange(input.checked); render(); });
    row.appendChild(input);
    if (colour) {
      var sw = document.createElement('span');
      sw.className = 'swatch';
      sw.style.background = colour;
      row.appendChild(sw);
    }
    row.appendChild(document.createTextNode(label));
    controlsBox.appendChild(row);
    return input;
  }

  var legend = document.getElementById('legend');
  function showLegend(on) {
    legend.hidden = !on;
  }
  if (data.distance) {
    var d = data.distance;
    legend.innerHTML = '<div>result: distance to the ground truth</div><div class="bar" style="background: linear-gradient(to right, ' +
      d.colors.join(', ') + ')"></div><div class="ends"><span>0</span><span>' + (100 * d.max / 2).toPrecision(2) +
      '%</span><span>&ge; ' + (100 * d.max).toPrecision(2) + '% of its radius</span></div>';
  }

  var loader = new T.GLTFLoader();
  data.layers.forEach(function (layer) {
    var material = new T.MeshStandardMaterial({
      color: new T.Color(layer.color), roughness: 0.5, metalness: 0.05, side: T.DoubleSide,
      transparent: layer.opacity < 1, opacity: layer.opacity, depthWrite: layer.opacity >= 1,
    });
    var group = new T.Group();
    group.visible = layer.visible;
    scene.add(group);
    var hasColours = false;
    addToggle(layer.label + (layer.faces < layer.faces_full ? ' (decimated)' : ''), layer.color, layer.visible,
              function (on) { group.visible = on; if (hasColours) showLegend(on && material.vertexColors); });
    loader.parse(base64ToBuffer(layer.glb), '', function (gltf) {
      gltf.scene.traverse(function (node) {
        if (!node.isMesh) return;
        if (!node.geometry.getAttribute('normal')) node.geometry.computeVertexNormals();
        if (node.geometry.getAttribute('color')) hasColours = true;
        node.material = material;
        node.renderOrder = layer.opacity < 1 ? 1 : 0;
      });
      group.add(gltf.scene);
      if (hasColours) {
        material.vertexColors = true;
        material.color.set(0xffffff);
        showLegend(group.visible);
        addToggle('colour the result by its distance to the ground truth', null, true, function (on) {
          material.vertexColors = on;
          material.color.set(on ? 0xffffff : layer.color);
          material.needsUpdate = true;
          showLegend(on && group.visible);
        });
      }
      log.layers += 1;
      window.lgPut();
      render();
    }, function (error) {
      console.error('cannot read the ' + layer.label + ' mesh: ' + error);
    });
  });

  var frustaGeometry = new T.BufferGeometry();
  frustaGeometry.setAttribute('position', new T.Float32BufferAttribute(data.frusta, 3));
  var frusta = new T.LineSegments(frustaGeometry, new T.LineBasicMaterial({ color: 0x59636f }));
  scene.add(frusta);
  addToggle('cameras (' + data.views.length + ')', '#59636f', true, function (on) { frusta.visible = on; });

  if (data.views.length) {
    var select = document.createElement('select');
    var free = document.createElement('option');
    free.textContent = 'look from: overview';
    free.value = '';
    select.appendChild(free);
    data.views.forEach(function (_, i) {
      var o = document.createElement('option');
      o.value = String(i);
      o.textContent = 'look from: view ' + String(i).padStart(2, '0');
      select.appendChild(o);
    });
    select.addEventListener('change', function () {
      if (select.value === '') home(); else fromView(Number(select.value));
    });
    controlsBox.appendChild(select);
  }

  home();
  resize();
})();
