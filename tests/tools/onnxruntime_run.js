// Runs an ONNX model in ONNX Runtime (onnxruntime-node, the CPU runtime) on one float32 input.
//   node onnxruntime_run.js MODEL.onnx INPUT.f32 B,C,H,W OUTPUT.f32
// INPUT.f32 and OUTPUT.f32 are raw little-endian float32 in C order; the output's shape is printed
// as JSON ({"output":"image","dims":[...]}). Node finds the runtime through NODE_PATH
// (scripts/setup.sh installs it under ~/.cache/flatnet; tests/test_onnx.cpp sets NODE_PATH).
'use strict';
const fs = require('fs');
const ort = require('onnxruntime-node');

async function main() {
  const [modelPath, inputPath, shapeText, outputPath] = process.argv.slice(2);
  if (!outputPath) throw new Error('usage: node onnxruntime_run.js MODEL INPUT.f32 B,C,H,W OUTPUT.f32');
  const dims = shapeText.split(',').map(Number);
  const bytes = fs.readFileSync(inputPath);
  const expected = dims.reduce((a, b) => a * b, 1) * 4;
  if (bytes.length !== expected) throw new Error(`${inputPath}: ${bytes.length} bytes, expected ${expected}`);
  const data = new Float32Array(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length));
  const session = await ort.InferenceSession.create(modelPath, {executionProviders: ['cpu']});
  const feeds = {[session.inputNames[0]]: new ort.Tensor('float32', data, dims)};
  const results = await session.run(feeds);
  const name = session.outputNames[0];
  const out = results[name];
  fs.writeFileSync(outputPath, Buffer.from(out.data.buffer, out.data.byteOffset, out.data.byteLength));
  console.log(JSON.stringify({output: name, dims: out.dims}));
}

main().catch((e) => {
  console.error(`onnxruntime_run: ${e.message}`);
  process.exit(1);
});
