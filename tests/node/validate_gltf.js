// Validate glTF files with the Khronos glTF-Validator (npm package gltf-validator) and print one
// JSON report per file on stdout: {"file", "numErrors", "numWarnings", "numInfos", "numHints", "messages"}.
// Usage: NODE_PATH=<folder holding node_modules/gltf-validator> node validate_gltf.js FILE.gltf ...
"use strict";
const fs = require("fs");
const path = require("path");
const validator = require("gltf-validator");

async function validate(file) {
  const full = path.resolve(file);
  const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(full)), {
    uri: path.basename(full),
    maxIssues: 100,
    externalResourceFunction: (uri) =>
      new Promise((resolve, reject) => {
        fs.readFile(path.resolve(path.dirname(full), decodeURIComponent(uri)), (err, data) =>
          err ? reject(err.toString()) : resolve(new Uint8Array(data)));
      }),
  });
  const issues = report.issues;
  return {
    file,
    numErrors: issues.numErrors,
    numWarnings: issues.numWarnings,
    numInfos: issues.numInfos,
    numHints: issues.numHints,
    messages: issues.messages.map((m) => `${m.severity} ${m.code} ${m.pointer || ""}: ${m.message}`),
  };
}

(async () => {
  const reports = [];
  for (const file of process.argv.slice(2)) reports.push(await validate(file));
  process.stdout.write(JSON.stringify(reports) + "\n");
})().catch((error) => {
  process.stderr.write(String(error) + "\n");
  process.exit(1);
});
