// Builds the viewer into web/dist (committed; embedded in the binary by src/server/web.rs):
//   app.js             web/src/app.js bundled with three.js and the addons it imports, minified
//   parse-worker.js    web/src/parse-worker.js (the mesh reader: three.js's loaders), the same way
//   index.html, style.css   copied
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
// Two bundles: the page, and the worker that reads mesh files (three.js's loaders live there).
for (const name of ['app', 'parse-worker']) {
  await build({
    entryPoints: [join(here, `src/${name}.js`)],
    bundle: true,
    format: 'esm',
    minify: true,
    target: ['es2022'],
    legalComments: 'eof',
    charset: 'utf8',
    outfile: join(dist, `${name}.js`),
    logLevel: 'warning',
  });
}
copyFileSync(join(here, 'src/index.html'), join(dist, 'index.html'));
copyFileSync(join(here, 'src/style.css'), join(dist, 'style.css'));
copyFileSync(join(here, 'node_modules/three/LICENSE'), join(dist, 'THREE-LICENSE.txt'));
console.log(`built ${dist}`);
