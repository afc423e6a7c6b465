// The API reference pages (/docs: Swagger UI, /redoc: ReDoc), their scripts served by this service (from the
// fastapi-offline package), nothing from outside. The schema is fetched with the token the dashboard saved
// (api.js), so a service with VOXNERF_API_TOKEN answers it; Swagger UI's "Try it out" requests carry the same
// token. The page's token form saves one, as the dashboard's does.
"use strict";

const referenceBox = document.getElementById("reference");

function showMessage(text) {
  const box = document.getElementById("message");
  box.textContent = text;
  box.hidden = false;
}

// Swagger UI on the fetched schema; every request it sends ("Try it out") carries the saved token.
function showSwagger(spec) {
  SwaggerUIBundle({
    spec,
    domNode: referenceBox,
    deepLinking: true,
    filter: true,  // a box that keeps the operations whose tag matches
    validatorUrl: null,  // the default would send the schema to validator.swagger.io
    presets: [SwaggerUIBundle.presets.apis],
    layout: "BaseLayout",
    requestInterceptor: (request) => {
      const token = savedToken();
      if (token) request.headers.Authorization = `Bearer ${token}`;
      return request;
    },
  });
}

// ReDoc on the fetched schema, with the system's fonts (its default names Roboto and Montserrat, which the page
// would have to load from Google). Its <style> elements carry the nonce this page's policy allows.
function showRedoc(spec) {
  const fonts = 'system-ui, -apple-system, "Segoe UI", Roboto, sans-serif';
  Redoc.init(spec, {
    nonce: document.querySelector('meta[name="style-nonce"]').content,
    nativeScrollbars: true,
    disableSearch: true,  // its search index runs in a worker made from a blob: URL, which script-src 'self' refuses
    theme: { typography: { fontFamily: fonts, headings: { fontFamily: fonts } } },
  }, referenceBox);
}

async function showReference() {
  try {
    const spec = await (await api("/openapi.json")).json();
    if (referenceBox.dataset.viewer === "redoc") showRedoc(spec); else showSwagger(spec);
    document.body.dataset.loaded = "true";
  } catch (err) {
    showMessage(`The API schema could not be read: ${err.message}`);
  }
}

document.getElementById("token").value = savedToken();
document.getElementById("token-form").addEventListener("submit", (event) => {
  event.preventDefault();
  saveToken(document.getElementById("token").value.trim());
  window.location.reload();
});
showReference();
