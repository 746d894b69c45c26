// The parts of three.js the report's 3D view uses (lookingglass/report/viewer.js), bundled by
// scripts/build_report_js.sh into one minified IIFE exposing the global `LG3`.
export {
  AmbientLight, Box3, BufferGeometry, Color, DirectionalLight, DoubleSide, Float32BufferAttribute,
  Group, HemisphereLight, LineBasicMaterial, LineSegments, Mesh, MeshBasicMaterial, MeshStandardMaterial,
  PerspectiveCamera, Scene, Sphere, SRGBColorSpace, Vector3, WebGLRenderer, REVISION,
} from 'three';
export { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
export { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
