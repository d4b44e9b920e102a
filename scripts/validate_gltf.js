// Validates a glTF/glb file with the Khronos glTF-Validator (npm gltf-validator, Node API);
// prints its report as JSON on stdout. Usage: node scripts/validate_gltf.js MODULE_DIR FILE
// (MODULE_DIR: the node_modules folder holding gltf-validator, see scripts/install_test_tools.sh).
const path = require('path');
const fs = require('fs');
const validator = require(path.resolve(process.argv[2], 'gltf-validator'));
const file = process.argv[3];
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {uri: path.basename(file), maxIssues: 10000})
    .then((report) => console.log(JSON.stringify(report)))
    .catch((error) => { console.error(`glTF-Validator failed on ${file}: ${error}`); process.exit(2); });
