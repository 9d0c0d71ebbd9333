// Builds the viewer into web/dist (committed; embedded in the binary by src/server/web.rs):
//   app.js             web/src/app.js (the page), minified
//   parse-worker.js    web/src/parse-worker.js (the mesh reader: three.js's loaders)
//   shared.js          what both import (three.js's core), loaded once by each
//   index.html, style.css, icon.svg   copied
//   THREE-LICENSE.txt  three.js's licence (MIT) and its meshoptimizer decoder's notice
// Deterministic: the same lockfile gives the same bytes (CI rebuilds and diffs).
import { build } from 'esbuild';
import { copyFileSync, mkdirSync, readFileSync, writeFileSync } from 'node:fs';
import { dirname, join } from 'node:path';
import { fileURLToPath } from 'node:url';

const here = dirname(fileURLToPath(import.meta.url));
// WEB_DIST_OUT builds elsewhere (the CI check compares that build with the committed dist).
const dist = process.env.WEB_DIST_OUT || join(here, 'dist');
mkdirSync(dist, { recursive: true });
// Two entry points, the page and the worker that reads mesh files, with what both use (three.js's
// core) in one shared chunk: two self-contained bundles carried that code twice (318 KB more).
await build({
  entryPoints: [join(here, 'src/app.js'), join(here, 'src/parse-worker.js')],
  bundle: true,
  format: 'esm',
  splitting: true,
  minify: true,
  target: ['es2022'],
  legalComments: 'eof',
  charset: 'utf8',
  outdir: dist,
  entryNames: '[name]',
  chunkNames: 'shared',
  logLevel: 'warning',
});
copyFileSync(join(here, 'src/index.html'), join(dist, 'index.html'));
copyFileSync(join(here, 'src/style.css'), join(dist, 'style.css'));
copyFileSync(join(here, 'src/icon.svg'), join(dist, 'icon.svg'));
// three.js's licence, and the notice of the one addon it ships under its own (meshoptimizer's
// decoder, in parse-worker.js; its notice is a line comment, which minifying drops).
const meshopt = readFileSync(join(here, 'node_modules/three/examples/jsm/libs/meshopt_decoder.module.js'), 'utf8')
  .split('\n').slice(0, 2).map((l) => l.replace(/^\/\/ ?/, '')).join('\n');
writeFileSync(
  join(dist, 'THREE-LICENSE.txt'),
  `${readFileSync(join(here, 'node_modules/three/LICENSE'), 'utf8')}\n`
    + `three/addons/libs/meshopt_decoder.module.js (bundled in parse-worker.js):\n${meshopt}\n`,
);
console.log(`built ${dist}`);
