// The page's mesh reader, off the main thread: { id, bytes, format, align } in, the arrays to
// draw (or { id, error }) out. A file of tens of MB then parses while the page still scrolls.
import { meshArrays } from './parse.js';

self.onmessage = async ({ data }) => {
  const { id, bytes, format, align } = data;
  try {
    const a = await meshArrays(bytes, format, align);
    const transfer = [a.position.buffer, a.normal.buffer];
    if (a.index) transfer.push(a.index.buffer);
    self.postMessage({ id, ...a }, transfer);
  } catch (e) {
    self.postMessage({ id, error: String((e && e.message) || e) });
  }
};
