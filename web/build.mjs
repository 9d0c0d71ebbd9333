// Builds the viewer into web/dist (committed; embedded in the binary by src/server/web.rs):
//   app.js             web/src/app.js (the page), minified
//   parse-worker.js    web/src/parse-worker.js (the mesh reader: three.js's loaders)
//   shared.js          what both import (three.js's core), loaded once by each
//   index.html, style.css, icon.svg   copied
//   THREE-LICENSE.txt  three.js's licence (MIT), shipped with the bundle
// Deterministic: the same lockfile gives the same bytes (CI rebuilds and diffs).
import { build } from 'esbuild';
import { copyFileSync, mkdirSync } from 'node:fs';
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
copyFileSync(join(here, 'node_modules/three/LICENSE'), join(dist, 'THREE-LICENSE.txt'));
console.log(`built ${dist}`);
